#!/usr/bin/env bash
# The wheel is the package: build it, install it (not editable) into a fresh venv and, from a
# folder outside the checkout, run what a new user runs first: --version, models, demo, the
# README's "Five lines", and one generate, sample and evaluate each. Run by .ci/run after the
# tests; `bash .ci/wheel_check.sh` alone works too (after `make test` made .venv).
set -euo pipefail
cd "$(dirname "$0")/.."
REPO=$(pwd)
PY=${PY:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
TMP=$(mktemp -d "${TMPDIR:-/tmp}/hrn_pyg_wheel.XXXXXX")
trap 'rm -rf "$TMP"' EXIT
start=$SECONDS
step() { echo "== wheel check ($((SECONDS - start)) s): $*"; }

step "build the wheel"
.venv/bin/python -m pip wheel -q --no-deps --no-build-isolation -w "$TMP/dist" .
WHEEL=$(ls "$TMP"/dist/hrn_pyg-*.whl)
.venv/bin/python - "$WHEEL" <<'PY'
import sys, zipfile
names = set(zipfile.ZipFile(sys.argv[1]).namelist())
wanted = {f"hrn_pyg/data/builtin_scenes/{s}.toml" for s in
          ("soft_bounce", "cube_collision", "wedge", "multi_material", "cube_push", "tower")}
wanted |= {"hrn_pyg/checkpoints/manifest.json", "hrn_pyg/checkpoints/shapes.pt"}
assert wanted <= names, f"the wheel lacks {sorted(wanted - names)}"
PY

step "install it into a fresh venv (torch pinned first, then the wheel, not editable)"
"$PY" -m venv "$TMP/venv"
BIN="$TMP/venv/bin"
"$BIN/python" -m pip install -q -c constraints.txt torch==2.13.0
"$BIN/python" -m pip install -q -c constraints.txt "$WHEEL"
touch "$TMP/installed"

mkdir -p "$TMP/work"
cd "$TMP/work"   # outside the checkout: nothing of it on the path
"$BIN/python" - "$REPO" <<'PY'
import sys, pathlib, hrn_pyg
where = pathlib.Path(hrn_pyg.__file__).resolve()
assert "site-packages" in where.parts and pathlib.Path(sys.argv[1]).resolve() not in where.parents, where
print(f"hrn_pyg imported from {where.parent}")
PY

step "hrn-pyg --version, models"
"$BIN/hrn-pyg" --version
"$BIN/hrn-pyg" models > models.txt && head -3 models.txt

step "the README's Five lines"
"$BIN/python" - "$REPO/README.md" > five_lines.py <<'PY'
import re, sys
text = open(sys.argv[1]).read()
block = re.search(r"## Five lines\s+```python\n(.*?)```", text, re.S)
assert block, "README.md has no '## Five lines' python block"
print(block.group(1) + "print('README lines: futures', tuple(futures.shape))")
PY
"$BIN/python" five_lines.py

step "hrn-pyg generate, sample, evaluate (a shipped model by name)"
"$BIN/hrn-pyg" generate --scene cube_collision --episodes 1 --first-seed 9 --episode-steps 20 --out data/cube_collision --no-progress
"$BIN/hrn-pyg" sample --scene soft_bounce --k 2 --horizon 5 --out sample
"$BIN/hrn-pyg" evaluate --data data/cube_collision --model ours=cube_collision --model shapes \
    --horizons 5 --long-horizons 10 --no-figure --out eval

step "hrn-pyg demo"
"$BIN/hrn-pyg" demo --k 2 --out demo

step "the viewer extra: sample --export glb,ply,vtk, then hrn-pyg view's static page"
"$BIN/python" -m pip install -q -c "$REPO/constraints.txt" "$WHEEL[viewer]"
"$BIN/hrn-pyg" sample --scene soft_bounce --k 2 --horizon 3 --export glb,ply,vtk --out exported --no-progress
test -s exported/rollout.glb && test -s exported/vtk/future_01.pvd && test -s exported/ply/future_01/frame_0003.ply
"$BIN/hrn-pyg" view exported --no-serve
grep -q "Plotly.newPlot" exported/viewer.html
if command -v chromium >/dev/null 2>&1; then  # the page from disk, no server: Chromium's own screenshot
    timeout 120 chromium --headless --no-sandbox --disable-gpu --no-first-run --disable-background-networking \
        --disable-component-update --disable-sync --disable-quic --user-data-dir="$TMP/chromium" \
        --window-size=900,600 --virtual-time-budget=8000 --screenshot="$TMP/work/viewer.png" \
        "file://$TMP/work/exported/viewer.html" >/dev/null 2>&1
    "$BIN/python" - "$TMP/work/viewer.png" <<'PY'
import sys
import numpy as np
from PIL import Image
image = np.asarray(Image.open(sys.argv[1]).convert("RGB")).astype(int)
coloured = float(((image.max(axis=2) - image.min(axis=2)) > 60).mean())
assert coloured > 0.01, f"the static viewer drew nothing ({coloured:.2%} coloured pixels)"
print(f"static viewer from disk: {coloured:.1%} of the screenshot coloured")
PY
fi

if [ -n "$(find "$TMP/venv" -path '*site-packages/hrn_pyg/*' -newer "$TMP/installed" -type f ! -name '*.pyc' | head -1)" ]; then
    echo "wheel check: commands wrote into the installed package:"; find "$TMP/venv" -path '*site-packages/hrn_pyg/*' -newer "$TMP/installed" -type f ! -name '*.pyc'
    exit 1
fi
step "passed"
