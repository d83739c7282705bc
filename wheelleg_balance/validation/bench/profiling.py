"""
Where balance_node's time goes: py-spy samples of the running node, summarized.

Optional (``benchmark --profile``): py-spy is not a dependency of the package; install it into
your environment (``pip install py-spy``) to use this. py-spy samples the node from outside
(``--gil``: only stacks of the thread holding the GIL, i.e. Python actually running, which is
what competes with the control thread) and writes collapsed stacks; ``summarize`` turns them
into the share of samples per thread and the hottest functions, self and inclusive.
"""
from collections import Counter
import re
import shutil
import subprocess
from typing import Dict, List, Optional

#: Frames every stack passes through; they say nothing about where the time goes.
_BORING = re.compile(r'^(_run_code|_run_module_as_main|<module>|main|spin|Thread\.|_bootstrap)')


def py_spy() -> Optional[str]:
    """Path of the py-spy executable, or None."""
    return shutil.which('py-spy')


def start_recording(pid: int, duration: float, output: str,
                    rate: int = 250) -> subprocess.Popen:
    """Start py-spy on process pid for duration s (collapsed stacks with thread names)."""
    return subprocess.Popen(
        [py_spy() or 'py-spy', 'record', '--pid', str(pid), '--duration',
         str(max(1, int(duration))), '--rate', str(rate), '--gil', '--threads',
         '--nonblocking', '--format', 'raw', '--output', output],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _function(frame: str) -> str:
    """'name (path/file.py:123)' -> 'name (path/file.py)'."""
    return re.sub(r':\d+\)$', ')', frame)


def summarize(raw_path: str, top: int = 12) -> Dict:
    """
    Summarize py-spy collapsed stacks: {'samples', 'threads', 'self', 'inclusive'}.

    threads: {thread label: share of samples}; self / inclusive: [[function, share], ...]
    with shares in percent of all samples (one sample = one moment the GIL was held).
    """
    threads, self_time, inclusive = Counter(), Counter(), Counter()
    total = 0
    with open(raw_path) as f:
        for line in f:
            stack, _, count = line.rstrip('\n').rpartition(' ')
            if not stack or not count.isdigit():
                continue
            n = int(count)
            frames = stack.split(';')
            label = frames[0]
            match = re.match(r'thread \((\d+)\): ?(.*)', label)
            if match:
                label = match.group(2) or match.group(1)
                frames = frames[1:]
            total += n
            threads[label] += n
            if frames:
                self_time[_function(frames[-1])] += n
            for fn in {_function(fr) for fr in frames}:
                if not _BORING.match(fn):
                    inclusive[fn] += n
    pct = 100.0 / total if total else 0.0

    def rows(counter: Counter) -> List[list]:
        return [[name, round(n * pct, 1)] for name, n in counter.most_common(top)]

    return {'samples': total,
            'threads': {name: round(n * pct, 1) for name, n in threads.most_common()},
            'self': rows(self_time), 'inclusive': rows(inclusive)}
