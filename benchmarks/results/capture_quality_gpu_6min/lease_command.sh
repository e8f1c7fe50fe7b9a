#!/bin/bash
# Device lease script: S-NeRF (default) on fern and flower, capture split, seed 0, one process per
# scene side by side on one GPU; records and logs to $OUT. Args: PY DEVICE MINUTES LIMIT_S
PY=${1:-python3}; DEVICE=${2:-cuda}; MIN=${3:-6.5}; LIMIT=${4:-590}
T0=$(date +%s)
set -u
if [ "$DEVICE" = cuda ]; then
  mkdir -p /tmp/site && $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl \
    && tar xJf .whl/pycolmap.tar.xz -C /tmp/site || exit 1
  export PYTHONPATH=/tmp/site:$PWD/src
  nvidia-smi -L
fi
export OMP_NUM_THREADS=4 PYTHONUNBUFFERED=1
$PY -c "import torch, kornia, pycolmap, trimesh, numba; print('torch', torch.__version__, 'kornia', kornia.__version__, 'pycolmap', pycolmap.__version__, 'numba', numba.__version__, torch.cuda.get_device_name() if torch.cuda.is_available() else 'cpu')"
echo "setup done at $(( $(date +%s) - T0 )) s"
M1=$($PY -c "m=$MIN; print(' '.join(f'{x/m:.4f}' for x in (1,2,4,6) if x < m))")
for s in fern flower; do
  $PY benchmarks/capture_quality.py --scenes $s --methods snerf --minutes $MIN --marks $M1 1 --threads 4 \
    --llff-root .gpudata/nerf_llff_data --set train.device=$DEVICE \
    --reference benchmarks/results/colour_reach_study/results.json --out /tmp/cqo_$s --work /tmp/cqw --quiet \
    > $OUT/${s}_snerf.log 2>&1 &
done
collect() {
  (cd /tmp/cqw && tar czf $OUT/records.tgz $(find . -name record.json -o -name calibration.json -o -name metrics.json -o -name 'train_log*' 2>/dev/null | grep -v '/eval_.*/.*/' ) 2>/dev/null)
  nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv 2>/dev/null >> $OUT/gpu.txt
}
# watchdog: collect whatever exists shortly before the command's limit
( while sleep 10; do
    [ $(( $(date +%s) - T0 )) -ge $(( LIMIT - 20 )) ] && { collect; break; }
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null >> $OUT/gpu.txt
  done ) &
WD=$!
wait %1 %2 2>/dev/null; wait $(jobs -p | grep -v $WD) 2>/dev/null
echo "training and scoring done at $(( $(date +%s) - T0 )) s"
collect
kill $WD 2>/dev/null
LEFT=$(( LIMIT - 15 - ($(date +%s) - T0) ))
if [ "$DEVICE" = cuda ] && [ $LEFT -gt 40 ]; then
  timeout $LEFT $PY -m pytest -q -p no:cacheprovider tests/test_free_path.py tests/test_colour_reach.py -k cuda > $OUT/pytest.log 2>&1
  echo "pytest rc $?"
fi
cat $OUT/*_snerf.log
echo "end at $(( $(date +%s) - T0 )) s"
