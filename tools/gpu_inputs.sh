#!/usr/bin/env bash
# The inputs of the prepared GPU run (tools/gpu_check.sh), made here before a session's device call:
# the device's image lacks kornia, holds no data, and reaches no network.
#
#   bash tools/gpu_inputs.sh [--vp]   (from the repository root; FR_DATA or ../shared/data; < 1 min)
#
# Writes, all ignored by git and carried by the call (`carry: [".whl", "data_local/gpu"]`):
#   .whl/                  kornia and kornia_rs wheels for the device's Python 3.12 (7 MB)
#   data_local/gpu/        yorkurbandb/P*/P*.jpg (the YUD test photos) and yud_test.txt (13 MB),
#                          bit_identity.segments.npz (the segments of tools/bit_identity.py) and
#                          bit_identity_cpu.npz (this machine's answers, for the CPU / GPU report);
#                          with --vp also nyu_vp/data/ (NYU-VP's val files and vps_0000.csv, 17 MB)
#                          and models/consac/ (CONSAC's weights: user-supplied, never committed) for
#                          gpu_check.sh's vp phase.
# A call carries at most 64 MiB with the working tree (about 30 MB): --vp leaves little room.
set -euo pipefail
DATA=${FR_DATA:-../shared/data}
GPU=data_local/gpu
[ -d "$DATA/yorkurbandb" ] || { echo "gpu_inputs: no yorkurbandb under $DATA (set FR_DATA)" >&2; exit 2; }
mkdir -p .git/info
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude
KORNIA=$(python3 -c "import importlib.metadata as m; print(m.version('kornia'))")
KORNIA_RS=$(python3 -c "import importlib.metadata as m; print(m.version('kornia_rs'))")
rm -rf .whl && mkdir -p .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d .whl "kornia==$KORNIA" "kornia_rs==$KORNIA_RS"

rm -rf "$GPU/yorkurbandb" "$GPU/nyu_vp" "$GPU/models"
mkdir -p "$GPU/yorkurbandb"
FR_DATA=$DATA python3 - "$GPU/yud_test.txt" <<'EOF'
import sys
from fr_eval.datasets.registry import load_dataset
names = [sample.name for sample in load_dataset("yud", split="test")]
open(sys.argv[1], "w").write("\n".join(names) + "\n")
EOF
while read -r name; do
  mkdir -p "$GPU/yorkurbandb/$name" && cp "$DATA/yorkurbandb/$name/$name.jpg" "$GPU/yorkurbandb/$name/"
done < "$GPU/yud_test.txt"
if [ "${1:-}" = "--vp" ]; then
  mkdir -p "$GPU/nyu_vp/data" "$GPU/models"
  cp "$DATA"/nyu_vp/PROVENANCE.md "$GPU/nyu_vp/"
  cp "$DATA"/nyu_vp/data/vps_0000.csv "$GPU/nyu_vp/data/"
  for i in $(seq 1000 1223); do cp "$DATA"/nyu_vp/data/*_$(printf %04d "$i").csv "$GPU/nyu_vp/data/"; done
  CONSAC=${FR_CONSAC_WEIGHTS:-$(dirname "$DATA")/models/consac}
  if [ -d "$CONSAC" ]; then cp -r "$CONSAC" "$GPU/models/consac"; fi
fi
FR_DATA=$DATA python3 tools/bit_identity.py save "$GPU/bit_identity_cpu.npz" --segments "$GPU/bit_identity.segments.npz"
du -sh .whl "$GPU"
