#!/usr/bin/env bash
# benchmarks/device_check.py on a lent GPU machine, from the repository root; the printed table is
# also written to $OUT/device_check.md (OUT: the device tool's folder, else /tmp). Arguments pass
# through, e.g. `benchmarks/device_check.sh --train-seconds 120` or `--cpu`.
set -euo pipefail
cd "$(dirname "$0")/.."
out="${OUT:-/tmp}/device_check.md"
PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" "${PYTHON:-python}" benchmarks/device_check.py "$@" | tee "$out"
