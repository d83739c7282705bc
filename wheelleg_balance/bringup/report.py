"""The outcome of the bring-up checks: one ``Check`` per finding, a ``Report`` of them all."""
from dataclasses import dataclass, field
from typing import Callable, List

#: Levels, from harmless to blocking.
PASS, INFO, WARN, FAIL = 'PASS', 'INFO', 'WARN', 'FAIL'


@dataclass(frozen=True)
class Check:
    """
    One finding.

    level: PASS, INFO, WARN or FAIL; item: what was checked (e.g. 'can0', 'left wheel (ID 1)');
    text: what was found and why it matters; fix: what to do, one line each (commands exactly
    as they are to be typed).
    """

    level: str
    item: str
    text: str
    fix: List[str] = field(default_factory=list)

    def lines(self) -> List[str]:
        """Return the check as printed: '[LEVEL] item: text', then the fixes indented."""
        out = ['[%s] %s: %s' % (self.level, self.item, self.text)]
        out += ['       fix: %s' % f for f in self.fix]
        return out


class Report:
    """The checks so far, printed as they come (``out``, default print)."""

    def __init__(self, out: Callable[[str], None] = print):
        self.checks: List[Check] = []
        self._out = out

    def add(self, check: Check) -> Check:
        """Record and print a check; return it."""
        self.checks.append(check)
        for line in check.lines():
            self._out(line)
        return check

    def extend(self, checks) -> None:
        """Record and print several checks."""
        for c in checks:
            self.add(c)

    def say(self, text: str) -> None:
        """Print a line that is not a check (a heading, an instruction)."""
        self._out(text)

    @property
    def failed(self) -> List[Check]:
        """Return the FAIL checks."""
        return [c for c in self.checks if c.level == FAIL]

    def summary(self) -> str:
        """Return one line: how many checks of each level."""
        levels = (PASS, INFO, WARN, FAIL)
        counts = {lvl: sum(c.level == lvl for c in self.checks) for lvl in levels}
        return 'checks: %d PASS, %d WARN, %d FAIL, %d INFO' % (
            counts[PASS], counts[WARN], counts[FAIL], counts[INFO])
