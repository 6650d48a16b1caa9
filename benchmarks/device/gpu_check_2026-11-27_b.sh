#!/bin/bash
# 2026-11-27 device check 2: GPDFN's table on the GPU (torch.unique + searchsorted), the fused stack as one
# block, one host copy of the loss values per step; CUDA tests, step profile (+ cProfile), ESGS training rerun.
set -u
# (as run, these lines were inline; moved to env.sh unchanged)
source benchmarks/device/env.sh
stamp "compile"
timeout 200 python3 -c "import gsplat.cuda._backend" 2>&1 | tail -1
stamp "CUDA tests"
timeout 60 python3 -m pytest -q -p no:cacheprovider tests/core/methods/test_gpdfn.py tests/core/methods/test_scaffold_gs.py -k "cuda or gpu or device" -rs 2>&1 | tail -4
stamp "step profile, cuda"
timeout 120 python3 benchmarks/profile_step.py $S --backend cuda --gaussians 100000 --width 320 --priors gt --steps 20 --warmup 3 --repeats 2 --arms 3dgs depth+normal gpdfn "full esgs" --profile --json $OUT/step_profile_cuda_2.json 2>&1 | grep -v "^\[" | tail -32
stamp "ESGS training on cuda (rerun of the first check's run)"
timeout 90 python3 benchmarks/bench_cuda.py --scene $S --iterations 600 --arms cuda-esgs --esgs-priors gt --no-agreement --deadline-s 60 --json $OUT/cuda_esgs_2.json --runs /tmp/runs 2>&1 | grep "train_cuda_esgs_s0:" | tail -2
stamp done
