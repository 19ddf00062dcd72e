#!/usr/bin/env bash
# Smoke test of the RWRL harness, end to end at toy sizes: the committed cartpole demonstrators
# generate a tiny D^U and D^N (200-step episodes) in MuJoCo, a fresh `safedice serve` (temp
# dir, free port) takes them through the Python client, trains SafeDICE and BC for a few
# hundred iterations, and each policy's ONNX export runs in the simulator with onnxruntime;
# the metrics must come back finite. Needs requirements.txt only (no torch).
#
#   bash bench/rwrl/smoke.sh            # from the repository root
#   SMOKE_KEEP=1 bash bench/rwrl/smoke.sh   # keep the work folder and its report
#
# The safedice binary: $SAFEDICE_BIN, else target/release/safedice, else `safedice` on PATH.
# Python: $RWRL_PYTHON, else bench/rwrl/.venv (created with requirements.txt if missing).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
started=$(date +%s)

py="${RWRL_PYTHON:-}"
if [[ -z "$py" ]]; then
  if [[ ! -x "$here/.venv/bin/python" ]]; then
    echo "smoke: creating $here/.venv from requirements.txt"
    python3 -m venv "$here/.venv"
    "$here/.venv/bin/pip" install --quiet -r "$here/requirements.txt"
  fi
  py="$here/.venv/bin/python"
fi

if [[ -z "${SAFEDICE_BIN:-}" ]]; then
  if [[ -x "$root/target/release/safedice" ]]; then
    export SAFEDICE_BIN="$root/target/release/safedice"
  elif command -v safedice >/dev/null; then
    export SAFEDICE_BIN="$(command -v safedice)"
  else
    echo "smoke: no safedice binary (cargo build --release, or set SAFEDICE_BIN)" >&2
    exit 1
  fi
fi

# The work folder (data, policies, the report) is removed at exit unless SMOKE_KEEP=1.
work="$(mktemp -d)"
if [[ "${SMOKE_KEEP:-}" == 1 ]]; then
  trap 'echo "smoke: kept $work"' EXIT
else
  trap 'rm -rf "$work"' EXIT
fi
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 MUJOCO_GL=disable

# RWRL_DEMONSTRATORS: another folder of demonstrator .npz files (default: the committed ones).
run() { "$py" "$here/run.py" --work "$work" ${RWRL_DEMONSTRATORS:+--demonstrators "$RWRL_DEMONSTRATORS"} "$@"; }
run generate --env cartpole --unlabeled 6 --labeled 2 --max-steps 200 --lanes 3
run train --env cartpole --seeds 0 --algorithms safedice,bc --iterations 300 --discriminator-iterations 200
run evaluate --env cartpole --episodes 3 --max-steps 200 --lanes 3 --demonstrators-too
run report --out "$work/report"

"$py" - "$work" <<'EOF'
import json, math, sys
from pathlib import Path
work = Path(sys.argv[1])
evals = json.loads((work / "runs/cartpole/evaluations.json").read_text())
algos = {e["algorithm"] for e in evals}
assert {"safedice", "bc", "demonstrator (preferred)", "demonstrator (non_preferred)"} <= algos, algos
for e in evals:
    assert set(e["metrics"]) == {"normalized_return", "average_return", "average_cost", "cvar10_cost"}, e
    # Trained policies' evaluations are recorded in the service (external evaluations).
    assert e["algorithm"].startswith("demonstrator") or e.get("service_evaluation_id"), e
    assert all(math.isfinite(v) for v in e["metrics"].values()), e
    assert e["episodes"] == 3 and e["env"] == "cartpole", e
jobs = json.loads((work / "runs/cartpole/jobs.json").read_text())["jobs"]
assert all(j["status"] == "succeeded" for j in jobs), jobs
# The weighting stage's record: alpha-hat's interval holds alpha-hat, the AUC lies in [0, 1].
(w,) = [j["weighting"] for j in jobs if j["algorithm"] == "safedice"]
sd = next(j for j in jobs if j["algorithm"] == "safedice")
assert w["alpha_hat_lower"] - 1e-9 <= sd["alpha_hat"] <= w["alpha_hat_upper"] + 1e-9, (sd["alpha_hat"], w)
assert 0 <= w["discriminator_heldout_auc"] <= 1 and w["weighting_uniform"] in (0, 1), w
report = (work / "report/results.md").read_text()
assert "SafeDICE" in report and "alpha-hat [interval] (true 0.5)" in report, report
print(f"smoke: {len(evals)} evaluations, {len(jobs)} jobs succeeded")
EOF
# The report's table here, since its file goes with the work folder.
sed -n '/^|/p' "$work/report/results.md" | head -20
echo "smoke: passed in $(( $(date +%s) - started )) s"
