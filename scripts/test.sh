#!/usr/bin/env bash
# The test suite: bash scripts/test.sh [pytest args...]
#   bash scripts/test.sh -k belief -x          # the whole of test/, filtered
#   bash scripts/test.sh test/test_packaging.py  # only the paths given
# Bootstraps .venv/ on first use (scripts/bootstrap.sh), then runs python -m pytest -q test.
# The whole suite runs on two pytest-xdist workers (HRC_TEST_WORKERS=N for another count, 0 for
# none): the tests of the ROS graph one after the other on one worker, the plant's --apply tests
# and the computations on the other, whichever is free; on three or more the arm's graph tests
# form a unit of their own too (no faster on two cores, and timing flakes at that load:
# bench/README.md; test/conftest.py, "workers"); test paths given run in this process alone.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
source scripts/bootstrap.sh

# One DDS domain per run (1..100, from this shell's process id) so that two runs on one host
# do not see each other's nodes; an explicit ROS_DOMAIN_ID wins (the first worker's; worker k
# takes (ROS_DOMAIN_ID - 1 + 37 k) mod 100 + 1, so a run of N workers uses N domains of 1..100).
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( $$ % 100 + 1 ))}"
# numpy's BLAS on one thread in every process of the run, the warm-up's too (test/conftest.py:
# OpenBLAS's spinning threads took the core the other worker needed, 5x slower at load)
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
echo "[test] ROS_DOMAIN_ID=$ROS_DOMAIN_ID ROS_AUTOMATIC_DISCOVERY_RANGE=$ROS_AUTOMATIC_DISCOVERY_RANGE" >&2

# Test paths given (test/x.py, test/x.py::name): run those; otherwise the whole test/ folder.
targets=(test)
for arg in "$@"; do
  if [[ "$arg" != -* && -e "${arg%%::*}" ]]; then
    targets=()
    break
  fi
done
# The whole suite: compile numba's kernels into its cache first, each once and on both cores
# (hrc_ros/tools/warm.py; about 60 s from a fresh clone, nothing when the cache is current),
# not once in every test process that reaches them at the same time. Both builds of each
# parallel kernel: the serial builds alone (the suite's processes run HRC_KERNEL_THREADS=serial)
# left the parallel ones to the tests that compare or time them, 677 s of pytest against 589 s
# (bench/README.md). A failure is reported and the suite runs anyway: the kernels then compile
# as the tests reach them.
if [ "${#targets[@]}" -gt 0 ]; then
  HRC_KERNEL_THREADS=auto python -m hrc_ros.tools.warm --if-needed ||
    echo "[test] the warm-up failed (above); the kernels compile as the tests reach them" >&2
fi
workers=()
if [ "${#targets[@]}" -gt 0 ] && [ "${HRC_TEST_WORKERS:-2}" != 0 ]; then
  workers=(-n "${HRC_TEST_WORKERS:-2}")
fi
exec python -m pytest -q "${workers[@]}" "${targets[@]}" "$@"
