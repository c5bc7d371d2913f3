#!/usr/bin/env bash
# The paper-size learned magnifier's long run, on a lent GPU machine (the device tool's `run`; one call of at most
# 10 minutes, 15 minutes of device time a session). Resumable: each call continues from the checkpoint the last
# one brought back. From the repository root, in the device tool:
#   run(command="bash tools/train_magnet_gpu.sh", timeout_s=600, carry=["processing/weights/magnet_paper.pt.ckpt"])
# then copy $OUT's three files (weights, checkpoint, log) from the reply's files_at into processing/weights/ (the
# checkpoint is ignored by git; the weights and their log are committed).
# Its figures go in docs/magnification-learned.md: `odsplat train-mm` prints the validation, bench/magnify.py and
# bench/magnify_protocol.py --methods learned measure the weights on the clip and the protocol.
set -euo pipefail
MINUTES=${MINUTES:-8}                 # wall time of training in this call (the start and the copies come on top)
STEPS=${STEPS:-150000}                # the cosine schedule's length: the same in every call of one run
WEIGHTS=processing/weights/magnet_paper.pt
python3 -m pip install -q --no-deps --no-build-isolation -e . >/dev/null
resume=()
[ -f "$WEIGHTS.ckpt" ] && resume=(--resume)
nvidia-smi --query-gpu=name,memory.used,memory.total --format=csv,noheader || true
PYTHONUNBUFFERED=1 python3 -m odsplat -v train-mm -o "$WEIGHTS" --size paper --device cuda --workers 14 \
    --batch-size 32 --crop 96 --steps "$STEPS" --minutes "$MINUTES" --threads 2 "${resume[@]}"
if [ -n "${OUT:-}" ]; then
    cp "$WEIGHTS" "$WEIGHTS.ckpt" "${WEIGHTS%.pt}.log.json" "$OUT/"
fi
