#!/usr/bin/env bash
# Regenerate every published table and figure under results/ (CPU; timings: results/bench/).
# Usage: eval/reproduce.sh [--check] [STEP...]   steps: dataset fit reliability lodo yud zind sota crops detectors vp horizon distortion reproducibility bench
# --check: afterwards, compare every regenerated CSV under results/ with the committed one
# (fr_eval.protocols.check_tables: rtol 1e-6, timings ignored); exit 1 when one differs beyond it.
# (default: all, in this order: the reliability models are trained before the tables that use them).  Data root: $FR_DATA (default ../shared/data); generated views go
# to $FR_CACHE (default data_local/).
set -euo pipefail
cd "$(dirname "$0")/.."
FR=${FR:-.venv/bin/fr}
# The YUD crop sizes: one list, fr_eval.datasets.panoviews.YUD_CROP_SIZES (datasets yud-crop-<size>).
CROP_SIZES=$(.venv/bin/python -c "from fr_eval.datasets.panoviews import YUD_CROP_SIZES; print(*YUD_CROP_SIZES)")
export MPLBACKEND=${MPLBACKEND:-Agg}
check=0
if [ "${1:-}" = "--check" ]; then check=1; shift; fi
steps=("$@")
[ ${#steps[@]} -eq 0 ] && steps=(dataset fit reliability lodo yud zind sota crops detectors vp horizon distortion reproducibility bench)

for step in "${steps[@]}"; do
  echo "== $step"
  case $step in
    fit)  # Likelihood parameters from YUD train (results/likelihood_fit.md); the default config keeps
          # the paper's priors (chosen on the train splits: results/likelihood_selection/).
      $FR fit-likelihood --dataset yud --split train --out configs/likelihood_fitted.json --report results/likelihood_fit.md
      $FR fit-likelihood --dataset yud --split train --priors paper --out configs/likelihood.json --report ''
      for d in yud zind-fr; do
        $FR eval --dataset $d --split train --no-plots --out results/likelihood_selection/$d \
          --methods "fr,fr[likelihood=fitted],fr[likelihood=paper],fast-fr,fast-fr[likelihood=fitted]"
      done ;;
    dataset)  # ZInD-fR: 15 views per panorama, split by room; narrow cameras: YUD crops around the
              # calibrated principal point (33.0 and 39.2 deg HFOV); data_local/, not committed
      .venv/bin/python -m fr_eval.datasets.make_dataset --panoramas "${FR_DATA:-../shared/data}/zind_sample_tour/panos" \
        --yaw-csv "${FR_DATA:-../shared/data}/zind_sample_tour/manhattan_yaw_derived.csv" \
        --out "${FR_CACHE:-data_local}/zind-fr" --seed 0 --views-per-pano 15 --fovs 60,75,90,105,120 --test-fraction 0.5
      for s in $CROP_SIZES; do
        .venv/bin/python -m fr_eval.datasets.crop_views --dataset yud --size $s --out "${FR_CACHE:-data_local}/yud-crop-$s"
      done
      # synthetic streets (issue 67): choices learned on train, reported on test; rendered, no input data
      .venv/bin/python -m fr_eval.datasets.synthetic_streets --seed 0 --train 200 --test 200 \
        --out "${FR_CACHE:-data_local}/synthetic-streets" ;;
    yud)  # Issue "evaluation harness": YUD test, both principal points, deviation measures a-e.
          # Every table: the library's default FOV range ([30, 120]) with the
          # paper's [50, 130] rows ([range=paper]) next to it (issue 13).
      $FR eval --dataset yud --split test --out results/yud \
        --methods "fr,fr[range=paper],fast-fr,fast-fr[range=paper],oracle-fr,oracle-fr[range=paper]"
      $FR eval --dataset yud --split test --methods fr,fast-fr,oracle-fr --pp calibrated --out results/yud/calibrated_pp --no-plots
      $FR eval --dataset yud --split test --methods fr --measures a,b,c,d,e --out results/yud/measures --no-plots
      # focal fusion over YUD test (one camera): paper cues vs the shipped reliability model
      .venv/bin/python -m fr_eval.protocols.focal_fusion results/yud/predictions.csv --out results/reliability/focal_fusion.md ;;
    zind)  # Issue "panorama datasets": ZInD-fR test, per-FOV table, distribution figure
      $FR eval --dataset zind-fr --split test --out results/zind-fr \
        --methods "fr,fr[range=paper],fast-fr,fast-fr[range=paper]" ;;
    sota)  # Issue "baselines" + issue 13: every method that searches focal gets the same range
          # (--fov-range, default = the library default); the paper-range rows beside them.
      M="fr,fr[range=paper],fast-fr,fast-fr[range=paper],lee2009,lee2009[range=paper],simon2018,simon2018[range=paper],prior"
      $FR eval --dataset yud --split test --methods "$M" --out results/sota/yud
      $FR eval --dataset zind-fr --split test --methods "$M" --out results/sota/zind-fr ;;
    crops)  # Narrow cameras: YUD crops around the calibrated principal point (33.0 and 39.2 deg HFOV)
      for s in $CROP_SIZES; do  # built by the dataset step
        $FR eval --dataset yud-crop-$s --split test \
          --methods "fr,fr[range=paper],fast-fr,lee2009,simon2018,prior" --out results/yud-crop/$s
      done
      # the held-out accuracy table (results/cross_dataset/accuracy.*): its "shipped" column is sota's
      # and the crops' published runs, so it follows them (its runs: step lodo)
      .venv/bin/python -m fr_eval.protocols.lodo table ;;
    detectors)  # Issue "detectors": LSD vs MCMLSD (paper's Table 3); issue 37: LSD vs torch-lines
      for d in yud zind-fr; do
        $FR eval --dataset $d --split test --no-plots --out results/detectors/$d \
          --methods "fr,fr[detector=mcmlsd],fast-fr,fast-fr[detector=mcmlsd]"
      done
      for d in yud zind-fr $(printf 'yud-crop-%s ' $CROP_SIZES); do
        $FR eval --dataset $d --split test --no-plots --out results/detectors/torch-lines/$d \
          --methods "fr,fr[detector=torch-lines],fast-fr,fast-fr[detector=torch-lines]"
      done ;;
    reliability)  # Issue "reliability": models shipped in configs/, tables in results/reliability/;
                  # train splits of ZInD-fR, YUD and the YUD crops (the dataset step builds them)
      T=zind-fr,yud$(printf ',yud-crop-%s' $CROP_SIZES)
      $FR train-reliability --dataset $T --split train --method fast --no-cache \
        --report-dataset zind-fr --report-split test --compare-synthetic 300
      $FR train-reliability --dataset $T --split train --method fr --no-cache \
        --report-dataset zind-fr --report-split test ;;
    lodo)  # Issue 35: leave-one-dataset-out protocol over YUD, ZInD-fR, NYU-VP and the YUD crops
           # (results/cross_dataset/; per-image predictions cached in $FR_CACHE/lodo); the reliable
           # promise's conformal scales go to configs/reliability.json (before the tables that use it)
      .venv/bin/python -m fr_eval.protocols.lodo run   # its accuracy table: step crops (it reads sota's and crops' runs)
      .venv/bin/python -m fr_eval.protocols.lodo_reliability promise --write
      for rule in worst pooled; do
        .venv/bin/python -m fr_eval.protocols.lodo_reliability table --scale-rule $rule
        .venv/bin/python -m fr_eval.protocols.lodo_reliability table --scale-rule $rule --focal-limit 15 --tilt-limit 5
      done
      .venv/bin/python -m fr_eval.protocols.lodo_reliability table --bounds knn   # issue 35's bounds, for comparison
      .venv/bin/python -m fr_eval.protocols.lodo_reliability figure             # results/reliability/risk_coverage.png
      # issue 67: the horizon promise held out, its shipped scales (configs/reliability.json) and ecd-tune, a set no choice saw
      .venv/bin/python -m fr_eval.protocols.horizon_promise table
      .venv/bin/python -m fr_eval.protocols.horizon_promise promise --write
      .venv/bin/python -m fr_eval.protocols.horizon_promise final --dataset ecd-tune --split all
      # issue 45: the promise on torch-lines' segments vs LSD's, same photos (the promise's validated_detectors)
      .venv/bin/python -m fr_eval.protocols.detector_reliability run
      .venv/bin/python -m fr_eval.protocols.detector_reliability table ;;       # results/reliability/torch_lines.*
    vp)  # Issue 47: vanishing points with CONSAC's metric (results/vp/); CONSAC needs its authors' weights
         # ($FR_CONSAC_WEIGHTS or ../shared/models/consac) and takes ~3 s per photo on one thread
      export OMP_NUM_THREADS=1 FR_THREADS=1
      M='fr,fast-fr,fr[atlanta=on],lee2009,simon2018,consac,consac-s'
      $FR eval --task vp --dataset nyu-vp --split val --methods "$M" --out results/vp/nyu-vp-val
      $FR eval --task vp --dataset yud+ --split test --methods "$M,consac[seed=2]" --out results/vp/yud-plus-test
      $FR eval --task vp --dataset yud --split test --methods "$M,consac[seed=2]" --out results/vp/yud-test
      $FR eval --task vp --dataset nyu-vp --split val --intrinsics unknown --out results/vp/consac-seeds-nyu-vp-val \
        --methods "consac[seed=1],consac[seed=2],consac[seed=3],consac[seed=4],consac[seed=5],consac-s[seed=1],consac-s[seed=2],consac-s[seed=3]"
      $FR eval --dataset yud --split test --methods "fr,fast-fr,lee2009,simon2018,consac,consac-s" --out results/vp/camera-yud-test
      $FR eval --dataset nyu-vp --split val --methods "fr,fast-fr,consac,consac-s" --out results/vp/camera-nyu-vp-val ;;
    horizon)  # Issue 54: the horizon benchmark (Lezama 2014's AUC; results/horizon/README.md) on YUD (ECCV test and
              # all 102 for the published rows), ecd-tune (the 25 tuning photos of the Eurasian Cities benchmark)
              # and NYU-VP val (fR's horizon bound); CONSAC as for vp (~3 s per YUD photo, ~30 s per ecd-tune photo)
      export OMP_NUM_THREADS=1 FR_THREADS=1
      M='fr,fast-fr,lee2009,simon2018,consac'
      $FR eval --task horizon --dataset ecd-tune --split all --methods "$M" --out results/horizon/ecd-tune-all
      $FR eval --task horizon --dataset yud --split test --methods "$M,oracle-fr" --out results/horizon/yud-test
      $FR eval --task horizon --dataset yud --split all --methods "$M,oracle-fr" --out results/horizon/yud-all
      $FR eval --task horizon --dataset nyu-vp --split val --methods fr,fast-fr --out results/horizon/nyu-vp-val
      # issue 67: extra horizontal families (results/horizon/families/): chosen on YUD and synthetic-streets
      # train, reported once on the test sets, NYU-VP val and ecd-tune
      P='fr,fr[families=auto]'; H=results/horizon/families
      for s in train test; do
        $FR eval --task horizon --dataset yud --split $s --methods "$P" --out $H/yud-$s --no-plots
        $FR eval --dataset yud --split $s --methods "$P" --out $H/yud-$s-camera --no-plots
        $FR eval --task horizon --dataset synthetic-streets --split $s --limit 60 --methods "$P" \
          --out $H/synthetic-streets-${s}60 --no-plots
        $FR eval --dataset synthetic-streets --split $s --limit 60 --methods "$P" --out $H/synthetic-streets-${s}60-camera --no-plots
      done
      $FR eval --task horizon --dataset nyu-vp --split val --methods "$P" --out $H/nyu-vp-val --no-plots
      $FR eval --task horizon --dataset ecd-tune --split all --methods "$P" --out $H/ecd-tune-all --no-plots
      # what fR's error is made of (results/horizon/analysis.md): fR variants cached in $FR_CACHE/horizon_analysis
      .venv/bin/python -m fr_eval.protocols.horizon_analysis run
      .venv/bin/python -m fr_eval.protocols.horizon_analysis report ;;
    distortion)  # Issue 46: wide-angle lenses. ZInD-fR-D (the ZInD-fR views through a division-model
                 # lens, k ~ U[-0.4, 0]) and YUD-D (the YUD 480x360 crops warped, k ~ U[-0.3, 0]) into
                 # $FR_CACHE; pinhole fR, fR / Fast-fR + division, auto on them, on the same views
                 # undistorted, YUD test and NYU-VP val (results/distortion/); the time: fr bench
      .venv/bin/python -m fr_eval.datasets.make_dataset --panoramas "${FR_DATA:-../shared/data}/zind_sample_tour/panos" \
        --yaw-csv "${FR_DATA:-../shared/data}/zind_sample_tour/manhattan_yaw_derived.csv" \
        --out "${FR_CACHE:-data_local}/zind-fr-d" --seed 0 --views-per-pano 15 --fovs 60,75,90,105,120 \
        --test-fraction 0.5 --k-range=-0.4:0
      .venv/bin/python -m fr_eval.datasets.crop_views --dataset yud --size 480x360 --k-range=-0.3:0 \
        --out "${FR_CACHE:-data_local}/yud-crop-480x360-d"
      M="fr;fr[distortion=division];fast-fr[distortion=division];fr[distortion=auto]"
      .venv/bin/python -m fr_eval.protocols.distortion_eval run --split train --datasets yud-crop-480x360 \
        --methods "fr[distortion=division]"   # the YUD lens's own k (train split)
      .venv/bin/python -m fr_eval.protocols.distortion_eval run --split test --methods "$M" \
        --datasets zind-fr-d,yud-crop-480x360-d,zind-fr,yud-crop-480x360,yud
      .venv/bin/python -m fr_eval.protocols.distortion_eval run --split val --methods "$M" --datasets nyu-vp
      .venv/bin/python -m fr_eval.protocols.distortion_eval report --out results/distortion
      $FR bench --threads 2 --sections distortion --out results/distortion/bench ;;
    reproducibility)  # Issue 52: one photo, one answer -- YUD test and NYU-VP val under batch sizes, workers,
                      # threads and CPU kernel sets, --shared-focal groups (results/reproducibility/)
      .venv/bin/python -m fr_eval.protocols.reproducibility run --label current
      .venv/bin/python -m fr_eval.protocols.reproducibility table --labels current ;;
    bench)  # Issue "speed": latency, throughput, memory, scaling (results/bench/)
      $FR bench --threads 2 --stress  # both cores of an idle 2-core machine (the target setting)
      # folder end to end, whole fr calibrate processes (re-append the hand-written paragraph of pipeline.md)
      .venv/bin/python -m fr_eval.bench.folder --copies 1,3 --workers 0,1,2,default --rounds 2 \
        --out results/bench/pipeline.md ;;
    *) echo "unknown step $step" >&2; exit 2 ;;
  esac
done
if [ $check -eq 1 ]; then
  .venv/bin/python -m fr_eval.protocols.check_tables results
fi
