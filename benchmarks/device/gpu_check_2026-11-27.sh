#!/bin/bash
# 2026-11-27 device check: CUDA tests, step profile (cuda and cpu on one machine), scale curve on the GPU,
# and cuda-vs-cpu training on one scene. Everything lands in $OUT (at most 8 files).
set -u
# (as run, these lines were inline; moved to env.sh unchanged)
source benchmarks/device/env.sh
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import torch, gsplat; print('torch', torch.__version__, 'gsplat', gsplat.__version__, 'cpus', __import__('os').cpu_count())"
stamp "compile (gsplat JIT on first call)"
timeout 240 python3 -c "
import time, torch; t=time.perf_counter()
from esgs.core.render.cuda import cuda_available; print(cuda_available())
import gsplat.cuda._backend as b; print('compiled in', round(time.perf_counter()-t,1), 's')" 2>&1 | tail -3
stamp "CUDA tests"
timeout 150 python3 -m pytest -q -p no:cacheprovider tests/core/render/test_cpu.py tests/core/render/test_gsplat_reference.py 2>&1 | tail -8
stamp "step profile, cuda"
timeout 150 python3 benchmarks/profile_step.py $S --backend cuda --gaussians 100000 --width 320 --priors gt --steps 20 --warmup 3 --repeats 2 --arms 3dgs depth+normal gpdfn "full esgs" --json $OUT/step_profile_cuda.json 2>&1 | grep -v "^\[" | tail -8
stamp "step profile, cpu (2 threads, same machine)"
timeout 120 python3 benchmarks/profile_step.py $S --backend cpu --threads 2 --gaussians 100000 --width 320 --priors gt --steps 10 --warmup 2 --repeats 2 --arms 3dgs "full esgs" --json $OUT/step_profile_cpu_same_machine.json 2>&1 | grep -v "^\[" | tail -5
stamp "scale curve, cuda"
timeout 150 python3 benchmarks/scale_curve.py $S --backend cuda --gaussians 10000 100000 300000 1000000 3000000 --widths 320 --steps 8 --warmup 2 --json $OUT/scale_curve_cuda.json 2>&1 | tail -7
stamp "cuda vs cpu training"
timeout 300 python3 benchmarks/bench_cuda.py --scene $S --iterations 600 --arms cuda-3dgs cpu-3dgs cuda-esgs --esgs-priors gt --deadline-s 200 --json $OUT/cuda_vs_cpu.json --runs /tmp/runs 2>&1 | grep -v "^\s*$" | tail -14
stamp done
