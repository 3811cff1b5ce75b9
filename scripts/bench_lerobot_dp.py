#!/usr/bin/env python3
"""CPU latency of LeRobot's DiffusionPolicy in the paper configuration (PyTorch reference).

    VENV=$(bash scripts/lerobot_venv.sh)
    OMP_NUM_THREADS=1 "$VENV/bin/python" scripts/bench_lerobot_dp.py --threads 1 --runs 50 --json /tmp/dp.json

Config: cameras ext1, ext2 at 3x128x128, centre crop 115x115 (eval), ResNet-18 + GroupNorm,
separate encoder per camera, spatial softmax 32 keypoints, state 7, action 7, n_obs_steps 2,
horizon 16, n_action_steps 8, U-Net down_dims (256, 512, 1024), kernel 5, n_groups 8, step
embedding 256, FiLM scale modulation, DDIM with 100 train / 16 inference steps. Batch 1, eval,
torch.inference_mode, float32, randomly initialised weights (timing does not depend on them).

Measured separately (wall clock, time.perf_counter):
  encoder_ms    DiffusionModel._prepare_global_conditioning: both rgb encoders on both obs
                steps (4 images of 3x128x128 -> crop -> ResNet-18 -> spatial softmax -> linear)
  unet_step_ms  one DiffusionConditionalUnet1d call (1x16x7, t, global_cond)
  chunk_ms      DiffusionModel.generate_actions: encoders + 16 U-Net steps + DDIM steps
Inputs are already-normalised tensors (the normaliser is a few elementwise ops).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np
import torch


def parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (also set OMP_NUM_THREADS)")
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--json", type=str, default=None, help="write the results here")
    ap.add_argument("--shared-encoder", action="store_true", help="one rgb encoder for both cameras")
    return ap.parse_args()


def stats(samples_s: list[float]) -> dict[str, float]:
    ms = np.asarray(samples_s) * 1e3
    return {
        "p50": float(np.percentile(ms, 50)),
        "p99": float(np.percentile(ms, 99)),
        "mean": float(ms.mean()),
        "min": float(ms.min()),
        "max": float(ms.max()),
    }


def timeit(fn, runs: int, warmup: int) -> list[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    args = parse()
    torch.set_num_threads(args.threads)

    import diffusers
    import lerobot
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

    cams = ["observation.images.ext1", "observation.images.ext2"]
    img = (3, 128, 128)
    config = DiffusionConfig(
        device="cpu",
        push_to_hub=False,
        input_features={
            **{c: PolicyFeature(type=FeatureType.VISUAL, shape=img) for c in cams},
            OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(7,)),
        },
        output_features={ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(7,))},
        n_obs_steps=2,
        horizon=16,
        n_action_steps=8,
        vision_backbone="resnet18",
        pretrained_backbone_weights=None,
        use_group_norm=True,
        spatial_softmax_num_keypoints=32,
        crop_shape=(115, 115),
        crop_is_random=True,
        use_separate_rgb_encoder_per_camera=not args.shared_encoder,
        down_dims=(256, 512, 1024),
        kernel_size=5,
        n_groups=8,
        diffusion_step_embed_dim=256,
        use_film_scale_modulation=True,
        noise_scheduler_type="DDIM",
        num_train_timesteps=100,
        beta_schedule="squaredcos_cap_v2",
        clip_sample=True,
        clip_sample_range=1.0,
        prediction_type="epsilon",
        num_inference_steps=16,
    )
    torch.manual_seed(0)
    policy = DiffusionPolicy(config).eval()
    model = policy.diffusion

    n_params = sum(p.numel() for p in policy.parameters())
    n_enc = sum(p.numel() for p in model.rgb_encoder.parameters())
    n_unet = sum(p.numel() for p in model.unet.parameters())

    g = torch.Generator().manual_seed(1)
    batch = {
        OBS_STATE: torch.rand((1, 2, 7), generator=g) * 2 - 1,
        OBS_IMAGES: torch.randn((1, 2, len(cams), *img), generator=g),
    }
    with torch.inference_mode():
        global_cond = model._prepare_global_conditioning(batch)
    x = torch.randn((1, 16, 7), generator=g)
    t = torch.full((1,), 90, dtype=torch.long)
    noise = torch.randn((1, 16, 7), generator=g)

    with torch.inference_mode():
        enc = timeit(lambda: model._prepare_global_conditioning(batch), args.runs, args.warmup)
        unet = timeit(lambda: model.unet(x, t, global_cond=global_cond), args.runs, args.warmup)
        chunk = timeit(lambda: model.generate_actions(batch, noise=noise), args.runs, args.warmup)

    result = {
        "torch": torch.__version__,
        "lerobot": lerobot.__version__,
        "diffusers": diffusers.__version__,
        "threads": args.threads,
        "omp_num_threads_env": os.environ.get("OMP_NUM_THREADS"),
        "torch_get_num_threads": torch.get_num_threads(),
        "runs": args.runs,
        "warmup": args.warmup,
        "separate_encoder_per_camera": not args.shared_encoder,
        "params": {"total": n_params, "rgb_encoders": n_enc, "unet": n_unet},
        "global_cond_dim": int(global_cond.shape[1]),
        "cpu": platform.processor() or platform.machine(),
        "encoder_ms": stats(enc),
        "unet_step_ms": stats(unet),
        "chunk_ms": stats(chunk),
    }
    print(
        f"torch {result['torch']}  lerobot {result['lerobot']}  threads {args.threads} "
        f"(OMP_NUM_THREADS={result['omp_num_threads_env']})  runs {args.runs}  warmup {args.warmup}"
    )
    print(f"params: total {n_params:,}  rgb encoders {n_enc:,}  unet {n_unet:,}")
    for name in ("encoder_ms", "unet_step_ms", "chunk_ms"):
        s = result[name]
        print(f"{name:13s} p50 {s['p50']:9.2f}  p99 {s['p99']:9.2f}  mean {s['mean']:9.2f}  [ms]")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
