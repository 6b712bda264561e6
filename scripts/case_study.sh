#!/usr/bin/env bash
# The case study: bash scripts/case_study.sh [hrc-case-study args...]
# Bootstraps .venv/ on first use (scripts/bootstrap.sh), then runs
# hrc-case-study --out out/case_study (extra arguments are passed on; a later --out wins).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
source scripts/bootstrap.sh

export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-42}"
echo "[case_study] hrc-case-study --out out/case_study $*" >&2
exec hrc-case-study --out out/case_study "$@"
