"""``esgs ndn``: build NDN training data, train the network, evaluate it.

- ``esgs ndn build-data --out DIR --scenes N``: render synthetic scenes (``esgs scene`` in
  child processes) into npz shards of view triples (resumable);
- ``esgs ndn train DATA --out MODEL_DIR [--steps N] [--resume] [--depth-state affine|log]``:
  train, with checkpoints;
- ``esgs ndn eval MODEL_DIR DATA``: AbsRel / delta1 (after scale-shift alignment) and normal
  angular errors on the held-out split;
- ``esgs ndn shard SCENE... --data DATA``: add any scene folder with ``priors/gt`` (e.g. one
  rendered from a real mesh with ``esgs scene --mesh``) to a data folder as a shard.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = "NDN diffusion prior: build training data, train, evaluate"


def _resolution(text: str) -> tuple[int, int]:
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH such as 160x90, got {text!r}") from None
    if width <= 0 or height <= 0:
        raise argparse.ArgumentTypeError(f"width and height must be positive, got {text!r}")
    return width, height


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..config import add_dataclass_arguments
    from ..ndn.config import NDNDataConfig, NDNDiffusionConfig, NDNModelConfig, NDNTrainConfig

    sub = parser.add_subparsers(dest="ndn_command", metavar="ACTION", required=True)
    build = sub.add_parser("build-data", help="render synthetic scenes into NDN training shards (resumable)")
    build.add_argument("--out", type=Path, required=True, help="data folder (shards/ and manifest.json)")
    add_dataclass_arguments(build, NDNDataConfig)
    build.add_argument("--resolution", type=_resolution, default=None, help="render size WxH (sets --width/--height)")

    train = sub.add_parser("train", help="train the NDN network on DATA/shards/train_*.npz")
    train.add_argument("data", type=Path, help="data folder from build-data")
    train.add_argument("--out", type=Path, required=True, help="model folder (config, checkpoints, weights.pt)")
    train.add_argument("--resume", action="store_true", help="continue from the latest checkpoint in --out")
    add_dataclass_arguments(train, NDNTrainConfig)
    add_dataclass_arguments(train, NDNModelConfig)
    add_dataclass_arguments(train, NDNDiffusionConfig)

    evaluate = sub.add_parser("eval", help="score a model on a data split (default: heldout)")
    evaluate.add_argument("model", type=Path, help="model folder or weights file")
    evaluate.add_argument("data", type=Path, help="data folder from build-data")
    evaluate.add_argument("--split", default="heldout", help="shard split to score (heldout, validation or train)")
    evaluate.add_argument("--steps", type=int, default=None, help="DDIM steps (default: the model's)")
    evaluate.add_argument("--seed", type=int, default=0, help="seed of the starting noise")
    evaluate.add_argument("--limit", type=int, default=0, help="score only the first N triples (0 = all)")
    evaluate.add_argument("--ensemble", type=int, default=None,
                          help="samples per view combined per pixel (default: the model's sample_ensemble)")
    evaluate.add_argument("--reduce", choices=("median", "mean"), default=None,
                          help="how an ensemble is combined (default: the model's sample_reduce)")
    evaluate.add_argument("--evidence", choices=("none", "sfm"), default="sfm",
                          help="what an evidence-conditioned network reads: the shards' SfM points (default) or nothing")
    evaluate.add_argument("--json", type=Path, default=None, help="also write the scores to this JSON file")

    shard = sub.add_parser("shard", help="add scene folders (with priors/gt) to a data folder as shards")
    shard.add_argument("scenes", type=Path, nargs="+", help="scene folders: images/, sparse/0, priors/gt")
    shard.add_argument("--data", type=Path, required=True, help="data folder (shards/ is created)")
    shard.add_argument("--split", default="heldout", help="split prefix of the shard names (default heldout)")
    shard.add_argument("--working-size", type=int, default=128, help="long side of the triples in pixels")
    shard.add_argument("--multiple", type=int, default=4, help="triple sizes are multiples of this")
    shard.add_argument("--sfm-points", action=argparse.BooleanOptionalAction, default=True,
                       help="triangulate the scene's images with its known poses and store the points' depth "
                            "(the evidence an evidence-conditioned network reads)")


def run(args: argparse.Namespace) -> int:
    from ..progress import ConsoleProgress

    bar = ConsoleProgress()
    try:
        if args.ndn_command == "build-data":
            from dataclasses import asdict

            from ..config import dataclass_from_args
            from ..ndn.config import NDNDataConfig
            from ..ndn.data import build_dataset

            if args.resolution:
                args.width, args.height = args.resolution
            settings = asdict(dataclass_from_args(NDNDataConfig, args))
            scenes = settings.pop("scenes")
            manifest = build_dataset(args.out, scenes, progress=bar, **settings)
            print(f"wrote {len(manifest['scenes'])} scene shards to {args.out / 'shards'}")
            return 0
        if args.ndn_command == "train":
            return _train(args, bar)
        if args.ndn_command == "shard":
            return _shard(args)
        from ..io_utils import atomic_write_json
        from ..ndn.infer import evaluate_ndn

        scores = evaluate_ndn(args.model, args.data, split=args.split, steps=args.steps, seed=args.seed,
                              limit=args.limit, ensemble=args.ensemble, reduce=args.reduce,
                              evidence_mode=args.evidence, progress=bar)
        bar.close()
        print(json.dumps(scores, indent=2))
        if args.json:
            atomic_write_json(args.json, scores)
        return 0
    finally:
        bar.close()


def _train(args: argparse.Namespace, bar) -> int:
    from ..config import dataclass_from_args
    from ..ndn.config import NDNConfig, NDNDiffusionConfig, NDNModelConfig, NDNTrainConfig
    from ..ndn.train import checkpoint_config, resume_source, saved_train_config, train_ndn
    from ..progress import JsonLinesProgress, combine

    model_config = dataclass_from_args(NDNModelConfig, args)
    manifest_path = args.data / "manifest.json"
    if args.working_size is None and manifest_path.exists():
        # inference must resize scenes to the resolution the network was trained at
        model_config.working_size = int(json.loads(manifest_path.read_text())["working_size"])
        model_config.validate()
    config = NDNConfig(model=model_config, diffusion=dataclass_from_args(NDNDiffusionConfig, args))
    source = resume_source(args.out) if args.resume else None
    # a resumed run keeps the training settings it was started with; the flags given override them
    train_config = dataclass_from_args(NDNTrainConfig, args,
                                       base=saved_train_config(args.out) if source is not None else None)
    # resuming or fine-tuning keeps the checkpoint's depth state unless --depth-state /
    # --log-depth-range ask for another one, which train_ndn then refuses
    if source is None and train_config.init and Path(train_config.init).exists():
        source = Path(train_config.init)
    if source is not None:
        saved = checkpoint_config(source).diffusion
        if args.depth_state is None:
            config.diffusion.depth_state = saved.depth_state
        if args.log_depth_range is None:
            config.diffusion.log_depth_range = saved.log_depth_range
    args.out.mkdir(parents=True, exist_ok=True)
    events = JsonLinesProgress(args.out / "events.jsonl")
    try:
        summary = train_ndn(args.data, args.out, train_config, config, resume=args.resume,
                            progress=combine(bar, events))
    finally:
        events.close()
    bar.close()
    print(json.dumps(summary, indent=2))
    if summary.get("status") == "interrupted":
        print(f"stopped at step {summary['steps']}; checkpoint saved, continue with: "
              f"esgs ndn train {args.data} --out {args.out} --resume")
        return 143  # 128 + SIGTERM, as `esgs train`: stopped on request, resumable
    return 0


def _shard(args: argparse.Namespace) -> int:
    from ..ndn.data import scene_triples, write_shard

    for scene in args.scenes:
        name = scene.name if scene.name.startswith(f"{args.split}_") else f"{args.split}_{scene.name}"
        triples = scene_triples(scene, args.working_size, args.multiple, sfm_points=args.sfm_points)
        path = args.data / "shards" / f"{name}.npz"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_shard(path, triples, {"scene": str(scene), "split": args.split})
        print(f"wrote {path} ({len(triples.names)} triples, {triples.views.shape[-1]}x{triples.views.shape[-2]})")
    return 0
