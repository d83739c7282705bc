# Source this to use the package built by scripts/setup.sh (venv + colcon install space).
_wlb_repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck disable=SC1091
source "$_wlb_repo/.venv/bin/activate"
# colcon's setup script reads unset variables; relax nounset while sourcing it.
case $- in *u*) _wlb_u=1; set +u;; *) _wlb_u=0;; esac
# shellcheck disable=SC1091
source "$_wlb_repo/.colcon/install/setup.bash"
[ "$_wlb_u" = 1 ] && set -u
unset _wlb_u
# The package's executables (what `ros2 run wheelleg_balance NAME` starts): main_job, benchmark,
# experiments, fault_report, balance_node, ... by name.
export PATH="$_wlb_repo/.colcon/install/wheelleg_balance/lib/wheelleg_balance:$PATH"
