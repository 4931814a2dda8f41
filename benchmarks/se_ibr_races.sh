#!/usr/bin/env bash
# The SE-IBR measurements of docs/se_ibr.md: solo on every shipped track (50 seeded races, seed 0) and on 256
# held-out circuit6 placements (seed 1); 1v1 and 2v2 self-matches on circuit6 with and without the sensitivity
# term; 1v1 duels SE-IBR against IBR from both slots and the IBR-vs-IBR control. One process at a time, one core.
# Usage: benchmarks/se_ibr_races.sh [OUT_DIR]   (from the repository root; then benchmarks/se_ibr_table.py OUT_DIR)
set -euo pipefail
R=${1:-/tmp/se_ibr}
mkdir -p "$R"
PY=${PYTHON:-.venv/bin/python}
run() {
  name=$1; shift
  OMP_NUM_THREADS=1 "$PY" -m spiral.eval.se_ibr_races "$@" --json "$R/$name.json" --save "$R/$name.pt" > "$R/$name.log"
  echo "$name done"
}
run solo_circuit6 solo
run solo_circuit6_holdout solo --runs 256 --seed 1
run solo_oval4 solo --track tracks/oval4.yaml
run solo_figure8 solo --track tracks/figure8.yaml
run solo_splits3d solo --track tracks/splits3d.yaml
run self_1v1_a1 1v1
run self_2v2_a1 2v2
run self_1v1_a0 1v1 --cfg '{"alpha": 0.0}'
run self_2v2_a0 2v2 --cfg '{"alpha": 0.0}'
run duel_a0_vs_a0 duel --cfg '{"alpha": 0.0}' --opponent-cfg '{"alpha": 0.0}'
run duel_a1_vs_a0 duel --cfg '{"alpha": 1.0}' --opponent-cfg '{"alpha": 0.0}'
run duel_a0_vs_a1 duel --cfg '{"alpha": 0.0}' --opponent-cfg '{"alpha": 1.0}'
