#!/usr/bin/env bash
# The prepared GPU run (one call of the lent device, re-runnable as it is): one answer per photo on
# the device (run to run, and against the CPU), CUDA tests, the device path from JPEG bytes to
# results stage by stage (tools/gpu_probe.py) and `fr bench --device cuda`.
#
#   bash tools/gpu_check.sh OUT [PHASES]     PHASES: comma list of setup,identity,tests,probe,cli,bench,vp,distortion
#                                            (default all but vp)
#
# Inputs travel with the working tree, made here first by `bash tools/gpu_inputs.sh` (`--vp` for the
# vp phase) and named in the call's carry (".whl", "data_local/gpu"): the kornia wheels in .whl/ (the
# device's image lacks kornia) and data_local/gpu/ (the YUD test photos, tools/bit_identity.py's
# segments and this machine's answers; NYU-VP's val files and CONSAC's weights with --vp). Each
# phase is time-boxed; everything it writes goes to OUT (the device tool's $OUT comes back).
# Device time is scarce (15 minutes a session, the machine's start included): name the phases the
# session needs, identity and bench first.
set -uo pipefail
DEST=${1:?usage: gpu_check.sh OUT [PHASES]}
PHASES=${2:-setup,identity,tests,probe,bench,cli,distortion}
# The phases write to a work folder; after each one everything so far is packed into
# DEST/gpu_run.tgz (the device tool brings back at most 8 files, and a run cut by its time limit
# still returns the last pack).
OUT=$(mktemp -d /tmp/gpu_check.XXXX)
mkdir -p "$DEST"
exec > >(tee -a "$OUT/console.log") 2>&1
pack() { tar czf "$DEST/gpu_run.tgz.part" -C "$OUT" . && mv "$DEST/gpu_run.tgz.part" "$DEST/gpu_run.tgz"; }
export PYTHONUNBUFFERED=1 MPLBACKEND=Agg PYTHONPYCACHEPREFIX=/tmp/pyc
unset PYTHONDONTWRITEBYTECODE   # the lent image sets it: every process would recompile every source
has() { [[ ",$PHASES," == *",$1,"* ]]; }
stamp() { echo "== $(date +%T) $*"; }

if has setup; then
  stamp setup
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv 2>&1 | tee "$OUT/nvidia-smi.txt"
  if [ -d .whl ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site
  fi
  python3 -m pip install -q --no-index --no-deps --no-build-isolation -e . 2>&1 | tail -2
  python3 -c "import torch, kornia, fr_torch, fr_eval; print('torch', torch.__version__, 'kornia', kornia.__version__, 'cuda', torch.cuda.is_available())"
  pack
fi
export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}

if has identity; then  # one answer per photo: the GPU run to run, the GPU against the device's CPU and this one's
  stamp identity
  SEG=data_local/gpu/bit_identity.segments.npz
  ID="timeout ${IDENTITY_TIMEOUT:-150} python3 tools/bit_identity.py"
  $ID save "$OUT/identity_cuda.npz" --segments $SEG --device cuda 2>&1 | tail -2
  $ID compare "$OUT/identity_cuda.npz" --segments $SEG --device cuda 2>&1 | tail -31 | tee "$OUT/identity_rerun.txt"
  $ID save "$OUT/identity_cpu.npz" --segments $SEG --threads 8 2>&1 | tail -1
  for against in "$OUT/identity_cpu.npz" data_local/gpu/bit_identity_cpu.npz; do  # the device's CPU, the CPU of the machine that made the inputs
    echo "GPU against $against:" | tee -a "$OUT/identity_report.txt"
    python3 tools/bit_identity.py report "$OUT/identity_cuda.npz" --against "$against" 2>&1 | tee -a "$OUT/identity_report.txt"
  done
  echo "the device's CPU against the inputs' CPU:" | tee -a "$OUT/identity_report.txt"
  python3 tools/bit_identity.py report "$OUT/identity_cpu.npz" --against data_local/gpu/bit_identity_cpu.npz 2>&1 \
    | tee -a "$OUT/identity_report.txt"
  pack
fi

if has tests; then
  stamp tests
  timeout ${TESTS_TIMEOUT:-90} python3 -m pytest -q -p no:cacheprovider tests/test_tensor_lines.py tests/test_device_pipeline.py tests/test_distortion.py \
    "tests/test_estimator.py::test_cuda_equals_cpu" "tests/test_speed_paths.py::test_cuda_grid_and_estimate_equal_cpu" \
    -k "cuda or decode or device or batch or lens" 2>&1 \
    | tee "$OUT/tests.txt" | tail -15
  pack
fi

if has probe; then
  stamp probe
  timeout ${PROBE_TIMEOUT:-300} python3 tools/gpu_probe.py --images data_local/gpu/yorkurbandb --test-list data_local/gpu/yud_test.txt \
    --out "$OUT" --device cuda --repeats ${PROBE_REPEATS:-2} --batches ${PROBE_BATCHES:-256,1024} --stages ${PROBE_STAGES:-pipeline,reliability_cost,pipeline_profile,accuracy} \
    2>&1 | grep -v '^USDT' | cut -c1-600
  pack
fi

if has bench; then
  stamp bench
  start=$(date +%s)
  timeout ${BENCH_TIMEOUT:-200} python3 -m fr_torch.cli bench --device cuda --sections device,detectors ${BENCH_ARGS:---repeats 3} --out "$OUT/bench" \
    --data-root data_local/gpu 2>&1 | tail -20
  echo "fr bench --device cuda: $(( $(date +%s) - start )) s" | tee "$OUT/bench_seconds.txt"
  pack
fi
if has cli; then  # whole processes on a folder of the YUD test photos, 10 times each
  stamp cli
  rm -rf /tmp/folder && mkdir -p /tmp/folder
  for k in 0 1 2 3 4 5 6 7 8 9; do for f in data_local/gpu/yorkurbandb/*/*.jpg; do ln -s "$PWD/$f" "/tmp/folder/${k}_$(basename "$f")"; done; done
  for mode in --fast ""; do
    start=$(date +%s.%N)
    timeout ${CLI_TIMEOUT:-60} python3 -m fr_torch.cli calibrate --device cuda $mode --no-progress /tmp/folder/*.jpg > /tmp/calibrate.jsonl 2>/tmp/calibrate.err
    end=$(date +%s.%N)
    python3 -c "import json,sys; r=[json.loads(l) for l in open('/tmp/calibrate.jsonl')]; t=$end-$start; print(f'fr calibrate --device cuda ${mode:-(fR)}: {len(r)} records, ok {sum(x[\"ok\"] for x in r)}, reliable {sum(bool(x[\"reliable\"]) for x in r)}, whole process {t:.1f} s = {len(r)/t:.0f} images/s')" | tee -a "$OUT/cli.txt"
    tail -2 /tmp/calibrate.err
    rm -rf /tmp/batch.parquet
    timeout ${CLI_TIMEOUT:-60} python3 -m fr_torch.cli batch --device cuda $mode --no-progress /tmp/folder --out /tmp/batch.parquet 2>&1 | tail -2 | tee -a "$OUT/cli.txt"
  done
  pack
fi

if has vp; then  # CONSAC and fR per photo on this machine's CPU (one thread) and GPU, the same 24 NYU-VP val photos
  stamp vp
  export FR_CONSAC_WEIGHTS=$PWD/data_local/gpu/models/consac
  for dev in cpu cuda; do
    OMP_NUM_THREADS=1 FR_THREADS=1 timeout ${VP_TIMEOUT:-80} python3 -m fr_torch.cli eval --task vp --dataset nyu-vp --split val \
      --limit 24 --intrinsics unknown --data-root data_local/gpu --methods fr,fast-fr,consac --device $dev --no-plots \
      --out "$OUT/vp_$dev" 2>&1 | tail -3
    cat "$OUT/vp_$dev/vp_summary.md" 2>/dev/null | head -8
  done
  pack
fi
if has distortion; then  # issue 46 on the device path: the YUD test photos and their bent copies (k = -0.2)
  stamp distortion
  rm -rf /tmp/lens && mkdir -p /tmp/lens
  python3 -c "
import cv2, glob, os
from fr_torch.images.lens import distort_image
for f in sorted(glob.glob('data_local/gpu/yorkurbandb/*/*.jpg')):
    image = cv2.imread(f); stem = os.path.basename(f)[:-4]
    cv2.imwrite(f'/tmp/lens/{stem}.jpg', image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    cv2.imwrite(f'/tmp/lens/{stem}_bent.jpg', distort_image(image, -0.2, (image.shape[1], image.shape[0])), [cv2.IMWRITE_JPEG_QUALITY, 95])
"
  for lens in pinhole division auto; do
    start=$(date +%s.%N)
    timeout ${LENS_TIMEOUT:-60} python3 -m fr_torch.cli calibrate --device cuda --distortion $lens --no-progress /tmp/lens/*.jpg \
      > "$OUT/distortion_$lens.jsonl" 2> "$OUT/distortion_$lens.err"
    end=$(date +%s.%N)
    echo "fr calibrate --device cuda --distortion $lens: $(wc -l < "$OUT/distortion_$lens.jsonl") records in $(python3 -c "print(round($end-$start, 1))") s" | tee -a "$OUT/distortion.txt"
    tail -1 "$OUT/distortion_$lens.err"
  done
  pack
fi
stamp done
pack
