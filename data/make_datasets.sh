#!/usr/bin/env bash
# Regenerate the bundled synthetic data sets (data/FOTAS, data/OTS) with the simulator.
# Run from the repository root:  bash data/make_datasets.sh
# Every run: Table II preset, stick option v_stick = 1e-5 m/s, 90 nm camera noise,
# 2 frames per step (the default frame rate), one seed per run.
set -euo pipefail
# k (N/m)  Nb (µN)  fp (Hz)  travel (µm)
CONDITIONS="
2.13  1   100  30
2.13  5   100  30
2.13  5   30   30
2.13  10  100  30
2.13  20  300  30
2.13  30  10   33.8
2.13  10  1000 30
20.3  30  100  30
20.3  30  30   30
20.3  60  100  30
"
for coating in FOTAS OTS; do
  seed=0
  while read -r k nb fp travel; do
    [ -z "$k" ] && continue
    name="${coating}_k${k}_Nb${nb}uN_fp${fp}Hz"
    python -m identify simulate --coating "$coating" --spring-constant "$k" \
      --normal-load-uN "$nb" --fp "$fp" --travel-um "$travel" --stick-speed 1e-5 \
      --noise-nm 90 --seed "$seed" --out "data/$coating/$name" --overwrite > /dev/null
    echo "data/$coating/$name"
    seed=$((seed + 1))
  done <<< "$CONDITIONS"
done
