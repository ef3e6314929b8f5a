"""`fastocc`: train, evaluate and benchmark the FastOcc network (torch side)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import click

from cli._common import debug_option, exit_on_interrupt, friendly_errors, stop_on_sigterm
from cli.options import (
    JSON_UNITS,
    STORE_HELP,
    ShownDefault,
    config_choice,
    device_option,
    json_option,
    progress_option,
    renamed_option,
    split_option,
    store_option,
    store_split,
)
from occdata.text import plural

__all__ = ["main"]

# Choices from the configs that define them (read when first used: these modules import torch).
PRESET_SOURCE = "fastocc.model.config:PRESETS"
HEAD_SOURCE = "fastocc.model.config:HeadKind"
TRAIN = "fastocc.train.config:TrainConfig"  # the fields that `fastocc train`'s options override


def _train_option(*decls: str, field: str | None = None, **kwargs: object):  # noqa: ANN202
    """A `fastocc train` option that overrides the TrainConfig field `field` (default: its name): None when
    not given, so a --config file's value stands; --help shows the field's default."""
    name = field or decls[-1].lstrip("-").replace("-", "_").split("/")[0]
    return click.option(*decls, default=None, cls=ShownDefault, config_field=f"{TRAIN}.{name}", **kwargs)


@click.group(context_settings={"help_option_names": ["-h", "--help"], "show_default": True})
@debug_option
@click.version_option(package_name="fastocc")
def main() -> None:
    """FastOcc: camera-only 3D semantic occupancy prediction in pure PyTorch.

    Reads stores written by `occdata build`. Every sub-command has its own --help.
    """


@main.command()
@click.option("--preset", "preset_names", type=config_choice(PRESET_SOURCE), multiple=True,
              help="Model preset (default nano); with --stage-split repeat it (default tiny, small and base).")
@click.option("--head", type=config_choice(HEAD_SOURCE, "all"), default="fastocc",
              help="'all' compares the heads in one run.")
@device_option()
@click.option("--batch-size", type=click.IntRange(min=1), default=1, show_default=True,
              help="Samples per forward pass (synthetic inputs).")
@renamed_option("--batch", "--batch-size", "batch_size", type=click.IntRange(min=1))
@click.option("--repeats", type=click.IntRange(min=1), default=5, help="Timed runs; the median is reported.")
@click.option("--warmup", type=click.IntRange(min=0), default=1, help="Untimed runs first.")
@click.option("--mode", type=config_choice("fastocc.bench:BenchConfig.mode"), default="infer",
              help="train = forward + backward.")
@click.option("--threads", type=click.IntRange(min=1), default=None, help="torch CPU threads (default: torch's).")
@click.option("--runtime", "runtimes", multiple=True, type=config_choice("fastocc.bench:RUNTIMES", "all"),
              help="End-to-end latency per frame (raw images -> preprocessing -> semantics) through the Predictor "
              "for eager PyTorch, torch.compile and/or ONNX Runtime in one run; repeat or use 'all'.")
@click.option("--stage-split", "stage_split", is_flag=True,
              help="The paper's Table III timing split: 2D / 2D-to-3D / 3D / total per preset, "
              "eager PyTorch and ONNX Runtime (--runtime torch|onnx to keep one), ratios between presets; on the "
              "CPU (--device auto means cpu here).")
@click.option("--input-hw", "input_hw", type=(int, int), default=None,
              help="With --stage-split: network input H W for every preset (default: each preset's).")
@renamed_option("--split", "--stage-split", "stage_split", is_flag=True)
@json_option()
def bench(
    preset_names: tuple[str, ...],
    head: str,
    device: str,
    batch_size: int,
    repeats: int,
    warmup: int,
    mode: str,
    threads: int | None,
    runtimes: tuple[str, ...],
    stage_split: bool,
    input_hw: tuple[int, int] | None,
    as_json: bool,
) -> None:
    """Per-stage latency, analytic FLOPs (MACs), parameters and peak memory on synthetic inputs.

    With --runtime: end-to-end latency per frame of eager PyTorch / torch.compile / ONNX Runtime instead.
    """
    from fastocc.bench import BenchConfig, format_report, run_benchmark  # torch import only when used
    from fastocc.dist import resolve_device
    from fastocc.model import HeadKind

    if stage_split:
        from fastocc.bench import SPLIT_RUNTIMES, SplitBenchConfig, format_split_report, run_split_benchmark

        if head != "fastocc" or mode != "infer" or device == "cuda" or "compile" in runtimes:
            raise click.UsageError("--stage-split measures the fastocc head in infer mode on the CPU, torch "
                                   "and/or onnx")
        chosen = SPLIT_RUNTIMES if not runtimes or "all" in runtimes else tuple(dict.fromkeys(runtimes))
        scfg = SplitBenchConfig(presets=tuple(dict.fromkeys(preset_names)) or ("tiny", "small", "base"),
                                runtimes=chosen, repeats=repeats, warmup=warmup, threads=threads, input_hw=input_hw)
        sresult = run_split_benchmark(scfg)
        click.echo(json.dumps(sresult, indent=2) if as_json else format_split_report(sresult))
        return
    if len(preset_names) > 1:
        raise click.UsageError("several --preset values need --stage-split")
    device = resolve_device(device)
    preset_name = preset_names[0] if preset_names else "nano"
    if runtimes:
        from fastocc.bench import RUNTIMES, RuntimeBenchConfig, format_runtime_report, run_runtime_benchmark

        if head == "all" or mode != "infer":
            raise click.UsageError("--runtime measures one head in infer mode (not --head all / --mode train)")
        chosen = RUNTIMES if "all" in runtimes else tuple(dict.fromkeys(runtimes))
        rcfg = RuntimeBenchConfig(preset=preset_name, head=HeadKind(head), runtimes=chosen, device=device,
                                  repeats=repeats, warmup=warmup, threads=threads)
        try:
            rresult = run_runtime_benchmark(rcfg)
        except ValueError as exc:
            raise click.ClickException(str(exc)) from None
        click.echo(json.dumps(rresult, indent=2) if as_json else format_runtime_report(rresult))
        return
    heads = tuple(HeadKind) if head == "all" else (HeadKind(head),)
    cfg = BenchConfig(
        preset=preset_name,
        heads=heads,
        device=device,
        batch=batch_size,
        repeats=repeats,
        warmup=warmup,
        mode=mode,  # type: ignore[arg-type]
        threads=threads,
    )
    try:
        result = run_benchmark(cfg)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(json.dumps(result, indent=2) if as_json else format_report(result))


@main.command("export")
@click.option("--checkpoint", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="fastocc checkpoint (carries its model config).")
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="ONNX file to write; the JSON sidecar goes next to it (model.onnx -> model.json).")
@click.option("--rig", default=None, help="Store or nuScenes tree whose first sample gives K, extrinsics and "
              "image sizes; its cameras must be the checkpoint's, in its order (default: a synthetic "
              "nuScenes-like rig of the checkpoint's cameras).")
@click.option("--opset", type=click.IntRange(min=1), default=18, show_default=True, help="ONNX opset (>= 18).")
@click.option("--frames", type=click.IntRange(min=1), default=2, show_default=True,
              help="Random frames in the parity check (temporal models: a moving stream).")
@friendly_errors
def export_cmd(checkpoint: Path, out: Path, rig: str | None, opset: int, frames: int) -> None:
    """Export a checkpoint to ONNX for one fixed camera rig, checked against PyTorch.

    Intrinsics, extrinsics and the test image transform are baked in (LSS indices and interpolation
    weights precomputed), so the graph uses standard ONNX operators only. The file is written only if
    ONNX Runtime (CPU) matches PyTorch: max |logit diff| <= 1e-3 and >= 99.9% identical argmax.
    """
    from fastocc.deploy import ExportConfig, export_onnx

    rep = export_onnx(ExportConfig(checkpoint=checkpoint, out=out, rig=rig, opset=opset, frames=frames))
    p = rep.parity
    click.echo(f"parity over {p.frames} frames: max |logit diff| {p.max_abs_diff:.2e} (limit "
               f"{p.limits['max_abs_diff']:g}), argmax agreement {100 * p.min_agreement:.4f}% (limit "
               f"{100 * p.limits['min_agreement']:g}%): {'PASS' if p.passed else 'FAIL'}")
    click.echo(f"wrote {rep.out} ({rep.size_mib:.1f} MiB, opset {rep.opset}) and {rep.sidecar} in "
               f"{rep.seconds:.1f} s; rig {rep.rig_hash[:12]}")


@main.command("show-batch")
@store_option(help=STORE_HELP)
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="PNG to write.")
@click.option("--index", "-i", type=click.IntRange(min=0), default=0, help="Store index of the sample.")
@click.option("--train", is_flag=True, help="Random training augmentation (default: the test transform).")
@click.option("--seed", type=int, default=0, help="Augmentation seed (with --train).")
@click.option("--height", type=click.IntRange(min=16), default=256)
@click.option("--width", type=click.IntRange(min=16), default=704)
@friendly_errors
def show_batch(store: str, out: Path, index: int, train: bool, seed: int, height: int, width: int) -> None:
    """Draw one sample as the loader delivers it: augmented images with depth targets, BEV labels and GT."""
    from fastocc.data import BevAugConfig, ImageAugConfig, SampleConfig
    from fastocc.data.show import ShowConfig, show_batch

    sample = SampleConfig(image=ImageAugConfig(height=height, width=width, train=train), bev=BevAugConfig(train=train))
    path = show_batch(ShowConfig(store=store, out=out, index=index, seed=seed, sample=sample))
    click.echo(f"wrote {path}")


@main.command()
@_train_option("--store", metavar="STORE", help=STORE_HELP)
@click.option("--config", "config_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="TOML file of TrainConfig fields (a [train] table or top level); options below override it.")
@_train_option("--preset", "preset_name", field="preset", type=config_choice(PRESET_SOURCE), help="Model preset.")
@_train_option("--head", type=config_choice(HEAD_SOURCE), help="3D-side head.")
@_train_option("--interp-features/--no-interp-features", "interp_features", field="interp_features",
               help="Ablation: --no-interp-features drops the interpolated image features from the FastOcc head "
               "(the BEV branch alone feeds the classifier).")
@_train_option("--view-transform", type=config_choice("fastocc.model.config:ViewTransformKind"),
               help="2D-to-3D view transform: lss (depth net + voxel pooling) or attention (spatial "
               "cross-attention from voxel queries, the paper's SurroundOcc* row with --head deconv).")
@_train_option("--bev-height", type=config_choice("fastocc.model.config:BevHeight"),
               help="With --no-interp-features: repeat the BEV feature along z or unfold its channels "
               "into the 16 height bins (channel-to-height).")
@_train_option("--temporal-fusion", type=config_choice("fastocc.model.config:TemporalFusionKind"),
               help="Models with history: concat (full maps in the queue), cached (each frame reduced "
               "once, when current; warp + small fusion per frame) or recurrent (one state carried forward: warp + "
               "a gated update per frame; temporal_channels and temporal_unroll in the config file).")
@_train_option("--epochs", type=click.IntRange(min=1), help="Epochs over the training split.")
@_train_option("--batch-size", type=click.IntRange(min=1),
               help="GLOBAL batch size (all processes); each process gets batch-size / world size.")
@_train_option("--lr", type=float,
               help="Learning rate at lr_base_batch (16); scaled to the global batch by lr_scaling (linear).")
@_train_option("--workers", type=click.IntRange(min=0), help="Loader worker processes per process.")
@_train_option("--pretrained", type=click.Path(dir_okay=False),
               help="Backbone weights: a torchvision ResNet state dict (e.g. resnet50-0676ba61.pth) or an "
               "mmdet/mmdet3d checkpoint's ResNet (e.g. FCOS3D's; docs/nuscenes.md); default: none (random "
               "initialisation).")
@_train_option("--out", help="Run folder.")
@click.option("--resume", is_flag=True, help="Continue the run in --out exactly where it stopped (--epochs may grow).")
@_train_option("--init-from", type=click.Path(dir_okay=False),
               help="Start a NEW run from this checkpoint's weights (model, and EMA if present); not with --resume.")
@_train_option("--warn-signal", type=config_choice("fastocc.train.config:WARN_SIGNALS"),
               help="Signal that, like SIGTERM, stops at the next step and saves last.pt.")
@device_option(config_field=f"{TRAIN}.device")
@_train_option("--val-every", type=click.IntRange(min=0), help="Validate every N epochs (0 = never).")
@progress_option()
@friendly_errors
def train(config_file: Path | None, resume: bool, progress: bool, **options: object) -> None:
    """Train FastOcc on a store: AdamW + warm-up/cosine by samples, EMA, validation, exact resume.

    Single process: `fastocc train --store data.zarr --out runs/nano`. Several GPUs or CPU processes:
    `torchrun --nproc_per_node N -m cli.fastocc_cli train ...` (DDP; only rank 0 writes). Ctrl-C saves
    `last.pt` and exits 130; SIGTERM or the warning signal (SIGUSR1) stop after the current step, save
    `last.pt` and exit 143 (preempted); `--resume` continues either. See docs/training.md.
    """
    from fastocc.train import load_config
    from fastocc.train import train as run_training
    from fastocc.train.preempt import EXIT_INTERRUPTED, EXIT_PREEMPTED

    names = {"preset_name": "preset", "batch_size": "batch_size", "val_every": "val_every"}
    overrides = {names.get(k, k): v for k, v in options.items()}
    cfg = load_config(config_file, overrides)
    # The loop saves on Ctrl-C itself and returns; a KeyboardInterrupt here came during start-up.
    with exit_on_interrupt("interrupted during start-up, before the first training step: nothing to save"):
        result = run_training(cfg, resume=resume, progress=progress)
    if result.interrupted:
        raise SystemExit(EXIT_INTERRUPTED)
    if result.preempted:
        raise SystemExit(EXIT_PREEMPTED)
    if result.is_main:  # under torchrun every rank returns here; one summary line
        best = "-" if result.best_miou is None else f"{100 * result.best_miou:.2f}%"
        which = "EMA" if result.best_is_ema else "raw"
        ranks = (f" ({len(result.steps_per_rank)} processes: {', '.join(map(str, result.steps_per_rank))} steps)"
                 if len(result.steps_per_rank) > 1 else "")
        click.echo(f"done: {plural(result.epochs_done, 'epoch')}, {plural(result.opt_steps, 'step')}{ranks}; best val "
                   f"mIoU ({which} "
                   f"weights) {best}; {result.out}")


_STORE = store_option(help=STORE_HELP)
_CKPT = click.option("--checkpoint", "checkpoint", required=True, type=click.Path(path_type=Path),
                     help="A checkpoint written by fastocc (carries its model config; no preset flags).")
_SPLIT = split_option(help="Dataset split of the store to run on.")
_TTA = click.option("--tta", is_flag=True, help="Average the class probabilities of the 4 BEV flips (x, y, both).")
_BATCH = click.option("--batch-size", type=click.IntRange(min=1), default=1, show_default=True)
_DEVICE = device_option()
_WORKERS = click.option("--workers", type=click.IntRange(min=0), default=0, show_default=True,
                        help="Data-loading worker processes.")


def _predict_config(checkpoint: Path, store: str, split: str | None, batch_size: int, workers: int, tta: bool,
                    device: str):  # noqa: ANN202
    """The PredictConfig of `fastocc predict` / `eval`. A missing checkpoint is said before anything about
    the store (the split default reads the store)."""
    from fastocc.checkpoint import check_checkpoint_file
    from fastocc.infer import PredictConfig

    check_checkpoint_file(checkpoint)
    return PredictConfig(store=store, split=store_split(store, split), batch_size=batch_size,
                         workers=workers, tta=tta, device=device)


@main.command()
@_CKPT
@_STORE
@_SPLIT
@click.option("--out", "out", required=True, type=click.Path(path_type=Path),
              help="Folder for OUT/<scene>/<token>/labels.npz (Occ3D layout, key 'semantics', uint8).")
@_TTA
@click.option("--png", type=click.IntRange(min=0), default=0, show_default=True,
              help="Also draw N pictures (cameras, 3D prediction | truth, top views) into OUT/pictures.")
@_BATCH
@_DEVICE
@_WORKERS
@progress_option()
@friendly_errors
@stop_on_sigterm
def predict(checkpoint: Path, store: str, split: str | None, out: Path, tta: bool, png: int, batch_size: int,
            device: str, workers: int, progress: bool) -> None:
    """Predict a store split with a checkpoint and write the Occ3D layout (score it with `occdata eval`).

    Samples run in scene order (the temporal queue of models with history is carried); each file is
    written atomically. Under torchrun each rank writes its shard of whole scenes (as `eval`).
    """
    from fastocc.infer.write import PredictRun, run_predict

    cfg = _predict_config(checkpoint, store, split, batch_size, workers, tta, device)
    summary = run_predict(PredictRun(checkpoint=checkpoint, out=out, predict=cfg, png=png, progress=progress))
    if os.environ.get("RANK", "0") != "0":  # under torchrun every rank holds the combined summary
        return
    click.echo(f"wrote {plural(summary.files, 'prediction')} to {summary.out} in {summary.seconds:.1f} s"
               + (f"; {len(summary.pictures)} pictures in {summary.out / 'pictures'}" if summary.pictures else ""))


@main.command("eval")
@_CKPT
@_STORE
@_SPLIT
@_TTA
@click.option("--mask", type=config_choice("fastocc.infer.evaluate:MaskKind"), default="camera", show_default=True,
              help="Voxels scored by mIoU (camera = the official Occ3D protocol). RayIoU uses no mask.")
@click.option("--no-rayiou", is_flag=True, help="Skip RayIoU (mIoU only).")
@json_option(f"Print the results as JSON ({JSON_UNITS}; null = class absent).")
@_BATCH
@_DEVICE
@_WORKERS
@progress_option()
@friendly_errors
@stop_on_sigterm
def eval_cmd(checkpoint: Path, store: str, split: str | None, tta: bool, mask: str, no_rayiou: bool, as_json: bool,
             batch_size: int, device: str, workers: int, progress: bool) -> None:
    """Score a checkpoint on a store split: Occ3D mIoU, RayIoU@1/2/4 m and inference frames/s.

    Predictions stay in memory; the metric code is `occdata eval`'s, so the numbers equal
    `fastocc predict` followed by `occdata eval` on the same checkpoint.
    """
    from fastocc.infer.evaluate import EvalRun, format_report, run_eval

    cfg = _predict_config(checkpoint, store, split, batch_size, workers, tta, device)
    report = run_eval(EvalRun(checkpoint=checkpoint, predict=cfg, rayiou=not no_rayiou, mask=mask,  # type: ignore[arg-type]
                              progress=progress))
    if os.environ.get("RANK", "0") == "0":  # under torchrun every rank holds the combined report
        click.echo(json.dumps(report.to_json(), indent=2) if as_json else format_report(report))


if __name__ == "__main__":
    main()
