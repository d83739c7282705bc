#!/usr/bin/env bash
# The math core's tests with the numpy and scipy that Ubuntu 24.04 ships (numpy 1.26.4,
# scipy 1.11.4: scripts/requirements-noble.txt), in a venv of their own (.venv-noble), against
# the source tree (no build). A core test is a test file that imports wheelleg_balance.core and
# whose every other import is the standard library, numpy, scipy, sympy, hypothesis, pytest or a
# helper module of test/ that is itself such: test/conftest.py (rclpy) is not loaded. Exit code
# is pytest's.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$repo/.venv-noble"
reqs="$repo/scripts/requirements-noble.txt"

# Noble's Python is 3.12: use one that runs (a pyenv shim may not), else the default python3.
python="${PYTHON_NOBLE:-}"
if [ -z "$python" ]; then
  for candidate in python3.12 "$HOME"/.pyenv/versions/3.12*/bin/python3.12 python3; do
    if "$candidate" -c 'import venv' >/dev/null 2>&1; then
      python="$candidate"
      break
    fi
  done
fi
if [ ! -x "$venv/bin/python" ]; then
  echo "[core-noble] creating $venv with $("$python" --version 2>&1)"
  "$python" -m venv "$venv"
fi
touch "$venv/COLCON_IGNORE"
stamp="$venv/.requirements.sha256"
want="$(sha256sum "$reqs" | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "[core-noble] installing $(grep -v '^#' "$reqs" | tr '\n' ' ')"
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$reqs"
  echo "$want" > "$stamp"
fi

cd "$repo"
mapfile -t tests < <("$venv/bin/python" - <<'EOF'
import ast
import pathlib
import sys

ALLOWED = {'numpy', 'scipy', 'sympy', 'hypothesis', 'pytest'}
test_dir = pathlib.Path('test')


def imports(path):
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module


def is_core(path, seen=()):
    for name in imports(path):
        top = name.split('.')[0]
        helper = test_dir / (top + '.py')
        if top in sys.stdlib_module_names or top in ALLOWED:
            continue
        if name == 'wheelleg_balance.core' or name.startswith('wheelleg_balance.core.'):
            continue
        if helper.is_file() and helper not in seen and is_core(helper, seen + (path,)):
            continue
        return False
    return True


def uses_core(path):
    return any(n == 'wheelleg_balance.core' or n.startswith('wheelleg_balance.core.')
               for n in imports(path))


for path in sorted(test_dir.glob('test_*.py')):
    if uses_core(path) and is_core(path):
        print(path)
EOF
)
if [ "${#tests[@]}" -eq 0 ]; then
  echo "[core-noble] no core test found" >&2
  exit 1
fi
"$venv/bin/python" -c 'import numpy, scipy, sys; print("[core-noble] Python %s, numpy %s, scipy %s" % (sys.version.split()[0], numpy.__version__, scipy.__version__))'
echo "[core-noble] ${#tests[@]} test files: ${tests[*]}"
export PYTHONPATH="$repo${PYTHONPATH:+:$PYTHONPATH}"
exec "$venv/bin/python" -m pytest --noconftest -p no:cacheprovider -q "${tests[@]}"
