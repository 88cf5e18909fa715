#!/usr/bin/env bash
# The GUI tests in other orders (issue 19): reversed, then shuffled with a few seeds (files, then tests in each
# file). Each run must pass; a failure names its order and seed, so it can be replayed with
#   .venv/bin/python -m pytest -p pytest_order --order-seed SEED tests/_napari   (PYTHONPATH=scripts, under Xvfb)
#   bash scripts/test_order.sh [SEED ...]        (default seeds: 1 2 3; the default suite's order is unchanged)
# Not part of the default run; CI (.ci/run) does one shuffled pass, seeded by the commit. This: about 3 passes.
set -euo pipefail
cd "$(dirname "$0")/.."
export QT_QPA_PLATFORM=xcb PYTHONPATH="scripts${PYTHONPATH:+:$PYTHONPATH}"
seeds=("$@"); [ "${#seeds[@]}" -gt 0 ] || seeds=(1 2 3)
run() { xvfb-run -a -s "-screen 0 1600x1200x24" .venv/bin/python -m pytest -q -p pytest_order -p no:cacheprovider "$@" tests/_napari; }
run --order-reverse
for seed in "${seeds[@]}"; do run --order-seed "$seed"; done
echo "GUI tests pass reversed and with seeds ${seeds[*]}"
