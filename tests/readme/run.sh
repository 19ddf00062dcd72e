#!/usr/bin/env bash
# Runs the README's walk-through as a user pastes it: every ```sh block after a
# `<!-- readme-test -->` marker, in order, in one bash in an empty directory, against a fresh
# server. Two substitutions only: `cargo run --release --` becomes the binary under test (CI has
# built it already), and the port is a free one (SAFEDICE_BIND and $API). Fails on any failing
# command, on a loop that never ends (a time limit), or if the walk-through's job and evaluation
# did not succeed.
#
#   cargo build --bin safedice && tests/readme/run.sh target/debug/safedice
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/../.." && pwd)"
BIN="$(cd "$(dirname "${1:-target/debug/safedice}")" && pwd)/$(basename "${1:-target/debug/safedice}")"
WORK="$(mktemp -d)"
WALK=
# The walk-through runs in its own process group (timeout makes one), so the server it starts in
# the background goes with it, whatever way it ends.
cleanup() {
  if [ -n "$WALK" ]; then kill -- "-$WALK" 2>/dev/null || true; wait "$WALK" 2>/dev/null || true; fi
  rm -rf "$WORK"
}
trap cleanup EXIT
PORT="$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')"

python3 - "$ROOT/README.md" "$BIN" "$PORT" > "$WORK/walkthrough.sh" <<'PY'
import re, sys
readme, binary, port = open(sys.argv[1]).read(), sys.argv[2], sys.argv[3]
blocks = re.findall(r"<!-- readme-test -->\n```sh\n(.*?)```", readme, re.S)
assert len(blocks) >= 2, f"expected the walk-through's blocks, found {len(blocks)}"
script = "\n".join(blocks)
script = script.replace("cargo run --release --", f"'{binary}'")
script = script.replace("http://127.0.0.1:8080", f"http://127.0.0.1:{port}")
print("set -euo pipefail")
print(f"export SAFEDICE_BIND=127.0.0.1:{port}")
print(script)
# What the walk-through must have achieved (the job is deleted at its end).
print('test "$(curl -s -o /dev/null -w "%{http_code}" -H "$AUTH" $API/v1/jobs/$JOB)" = 404')
print('echo; echo "README walk-through: job $JOB and evaluation $EVAL succeeded"')
PY

cd "$WORK"
started=$(date +%s)
timeout 900 bash walkthrough.sh > walkthrough.log 2>&1 &
WALK=$!
if ! wait "$WALK"; then
  echo "README walk-through failed; its output:"; tail -60 walkthrough.log; exit 1
fi
# The evaluation went with the job at the end; its listing is in the output.
grep -q '"status":"succeeded","metrics"' walkthrough.log || {
  echo "the walk-through's evaluation did not succeed"; tail -60 walkthrough.log; exit 1; }
tail -1 walkthrough.log
echo "README walk-through passed in $(( $(date +%s) - started )) s"
