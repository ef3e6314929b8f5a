"""`occdata`: turn nuScenes-format data (+ Occ3D labels) into one chunked zarr store (no torch)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click
import numpy as np

from cli._common import friendly_errors

__all__ = ["main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="fastocc")
def main() -> None:
    """occdata: nuScenes-format data and Occ3D labels -> one chunked zarr store.

    Every sub-command has its own --help.
    """


@main.command()
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Output directory (nuScenes-format root).")
@click.option("--scenes", default=2, show_default=True, type=click.IntRange(min=1), help="Number of scenes.")
@click.option("--samples", default=10, show_default=True, type=click.IntRange(min=1),
              help="Keyframes (2 Hz) per scene.")
@click.option("--seed", default=0, show_default=True, type=int, help="World seed (same seed, same bytes).")
@click.option("--width", default=1600, show_default=True, type=click.IntRange(min=16), help="Image width.")
@click.option("--height", default=900, show_default=True, type=click.IntRange(min=16), help="Image height.")
@click.option("--no-progress", is_flag=True, help="Hide the progress bar.")
@friendly_errors
def synth(out: Path, scenes: int, samples: int, seed: int, width: int, height: int, no_progress: bool) -> None:
    """Write a synthetic nuScenes-format world with Occ3D labels and exact depth maps.

    Tables (v1.0-mini), 6 ray-cast camera images, a 32-beam LiDAR sweep per keyframe,
    gts/<scene>/<sample>/labels.npz and depth/<sample_data_token>.npy. See docs/synth.md.
    """
    from occdata.synth import SynthConfig, synthesize

    root = synthesize(SynthConfig(out=out, scenes=scenes, samples=samples, seed=seed, width=width, height=height,
                                  progress=not no_progress))
    click.echo(f"wrote {scenes} scenes x {samples} samples to {root}")


@main.command()
@click.option("--root", required=True, type=click.Path(path_type=Path), help="nuScenes-format dataset root.")
@click.option("--version", default=None, help="Version folder (v1.0-trainval, v1.0-mini, ...); auto if only one.")
@click.option("--check-files/--no-check-files", default=True, show_default=True,
              help="Check that every keyframe image and LiDAR file exists.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@friendly_errors
def scan(root: Path, version: str | None, check_files: bool, as_json: bool) -> None:
    """Read and validate a nuScenes-format tree; print scenes and samples per split.

    Every foreign key is resolved; a broken tree fails with one line naming the file or token.
    """
    from occdata.nuscenes.summary import scan_tree

    summary = scan_tree(root, version, check_files)
    if as_json:
        click.echo(json.dumps(summary, indent=2))
        return
    click.echo(f"{summary['root']} [{summary['version']}]: {summary['scenes']} scenes, {summary['samples']} samples")
    for split, n in summary["samples_per_split"].items():
        click.echo(f"  {split:>12}: {summary['scenes_per_split'][split]:5d} scenes {n:7d} samples")


@main.command()
@click.option("--root", required=True, type=click.Path(path_type=Path), help="nuScenes-format dataset root.")
@click.option("--version", default=None, help="Version folder (v1.0-trainval, v1.0-mini, ...); auto if only one.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Output zarr store (a folder).")
@click.option("--gts", type=click.Path(path_type=Path), default=None,
              help="Occ3D-nuScenes labels folder (gts/<scene>/<sample_token>/labels.npz). Samples without a "
                   "label file are stored without labels (e.g. the test split).")
@click.option("--split", "splits", multiple=True,
              help="Keep only scenes of this split (repeatable): train, val, test, mini_train, mini_val, ...")
@click.option("--workers", type=int, default=1, show_default=True, help="Worker processes converting samples.")
@click.option("--resume", is_flag=True, help="Continue an interrupted build of the same inputs and options.")
@click.option("--on-error", type=click.Choice(["fail", "skip"]), default="fail", show_default=True,
              help="fail: stop at the first bad sample (everything before it stays committed); "
                   "skip: record the error in the store and go on.")
@click.option("--block-samples", type=int, default=32, show_default=True,
              help="Samples per shard (the unit of writing).")
@click.option("--image-scale", type=float, default=1.0, show_default=True,
              help="1.0 stores the original JPEG bytes; < 1 re-encodes the images at that scale.")
@click.option("--jpeg-quality", type=click.IntRange(1, 100), default=90, show_default=True,
              help="Quality (1-100) when re-encoding.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@friendly_errors
def build(root: Path, version: str | None, out: Path, gts: Path | None, splits: tuple[str, ...], workers: int,
          resume: bool, on_error: str, block_samples: int, image_scale: float, jpeg_quality: int,
          no_progress: bool) -> None:
    """Convert a nuScenes-format tree (+ Occ3D labels) into one chunked zarr store.

    Stores per keyframe: the 6 camera images, calibrations and poses, LiDAR depth targets,
    Occ3D labels and BEV multi-hot GT when labels exist, and 16-frame temporal indices.
    Kill it at any time and rerun with --resume: the result is identical.
    """
    from occdata.store.build import BuildConfig, build_store
    from occdata.store.sample import SampleOptions

    try:
        report = build_store(BuildConfig(
            root=root, out=out, version=version, gts=gts, splits=splits, workers=workers, resume=resume,
            on_error=on_error,  # type: ignore[arg-type]
            block_samples=block_samples, options=SampleOptions(image_scale=image_scale, jpeg_quality=jpeg_quality),
            progress=not no_progress,
        ))
    except KeyboardInterrupt:
        click.echo(f"\ninterrupted: every sample committed so far is kept in {out}; rerun the same command "
                   "with --resume to continue", err=True)
        sys.exit(130)
    click.echo(
        f"{report.store}: {report.n_done}/{report.n_samples} samples done, {report.n_errors} errors, "
        f"{report.n_labelled} labelled ({report.processed_now} processed in this run)"
    )
    if report.n_errors:
        click.echo("errors are recorded in the store: see `occdata info --store ...`", err=True)


_store_opt = click.option("--store", required=True, type=click.Path(path_type=Path), help="An occdata zarr store.")


@main.command("bev-gt")
@_store_opt
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@friendly_errors
def bev_gt(store: Path, no_progress: bool) -> None:
    """(Re)compute the BEV multi-hot ground truth from the stored voxel labels.

    One uint32 bit field per BEV cell (bit c: class c occurs in the column; bit 17 = free).
    `occdata build` already runs this when labels exist.
    """
    from occdata.store.bevgt import compute_bev_gt
    from occdata.store.reader import open_store

    open_store(store)  # validates the schema first
    n = compute_bev_gt(store, progress=not no_progress)
    click.echo(f"{store}: BEV GT written for {n} labelled samples")


@main.command()
@_store_opt
@click.option("--recompute", is_flag=True,
              help="Recompute for every labelled sample (default: only those without a shipped camera mask), "
                   "and report the agreement with the shipped Occ3D masks.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@friendly_errors
def visibility(store: Path, recompute: bool, no_progress: bool) -> None:
    """Camera and LiDAR visibility masks by ray casting through the voxel grid (3D DDA).

    A voxel is camera-visible if its centre projects inside some camera image with positive depth
    and no occupied voxel lies strictly between the camera centre and it. The LiDAR mask holds the
    voxels the stored keyframe LiDAR rays pass through or end in. Occupancy comes from the stored
    semantics, so only labelled samples are processed.
    """
    from occdata.store.visibility_cmd import compute_visibility

    report = compute_visibility(store, recompute=recompute, progress=not no_progress)
    click.echo(f"{store}: visibility computed for {report.computed} samples "
               f"({report.seconds_per_sample:.2f} s/sample); {report.skipped_unlabelled} unlabelled skipped")
    if report.agreement_iou:
        ious = np.array(list(report.agreement_iou.values()))
        click.echo(f"agreement with shipped mask_camera (IoU of visible sets) over {len(ious)} samples: "
                   f"mean {ious.mean():.4f}, min {ious.min():.4f}")


@main.command()
@_store_opt
@click.option("--json", "as_json", is_flag=True, help="Print everything as JSON (scene table included).")
@friendly_errors
def info(store: Path, as_json: bool) -> None:
    """Samples, scenes, arrays (shapes, dtypes, chunks), attrs and recorded errors of a store."""
    from occdata.store.inspect import store_info
    from occdata.store.reader import open_store

    summary = store_info(open_store(store))
    if as_json:
        click.echo(json.dumps(summary, indent=2))
        return
    a = summary["attrs"]
    click.echo(f"store {summary['store']}  (schema {a['schema']} v{a['schema_version']}, "
               f"{'complete' if a.get('complete') else 'INCOMPLETE: resume with occdata build --resume'})")
    click.echo(f"  source: {a['build_identity']['source_root']} [{a['build_identity']['source_version']}]")
    click.echo(f"  samples: {summary['samples']} (done {summary['done']}, errors {summary['errors']}, "
               f"pending {summary['pending']}); labelled {summary['labelled']}; "
               f"with visibility {summary['with_visibility']}; scenes {summary['scenes']}")
    click.echo(f"  images: {a['images']}")
    click.echo("  arrays:")
    for name, spec in summary["arrays"].items():
        shards = f" shards {tuple(spec['shards'])}" if spec["shards"] else ""
        click.echo(f"    {name:28s} {str(tuple(spec['shape'])):24s} {spec['dtype']:8s} "
                   f"chunks {tuple(spec['chunks'])}{shards}")
    if summary["recorded_errors"]:
        click.echo(f"  recorded errors ({len(summary['recorded_errors'])}):")
        for e in summary["recorded_errors"]:
            click.echo(f"    sample {e['index']} ({e['token']}): {e['reason']}")


@main.command()
@_store_opt
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@friendly_errors
def verify(store: Path, no_progress: bool) -> None:
    """Recompute every committed sample's checksums; report corruption with the sample it hits.

    Exits 1 if anything is wrong.
    """
    from tqdm import tqdm

    from occdata.store.reader import open_store
    from occdata.store.verify import pending_samples, verify_store

    reader = open_store(store)
    with tqdm(total=reader.n_samples, desc="verify", unit="sample", disable=no_progress) as bar:
        problems = verify_store(reader, progress=bar.update)
    pending = pending_samples(reader)
    if problems:
        for p in problems:
            click.echo(f"CORRUPT sample {p.index} ({p.token}): {p.array}: {p.reason}")
    if len(pending):
        click.echo(f"PENDING {len(pending)} of {reader.n_samples} samples not built yet (first: {int(pending[0])}, "
                   f"last: {int(pending[-1])}): the build was interrupted or is running; finish it with "
                   "`occdata build ... --resume`")
    if problems or len(pending):
        what = [f"{len(problems)} problem(s)"] if problems else []
        what += [f"{len(pending)} pending sample(s)"] if len(pending) else []
        raise click.ClickException(f"{' and '.join(what)} in {store}")
    click.echo(f"{store}: all {int((reader.state != 0).sum())} committed samples verified")


@main.command()
@_store_opt
@click.option("--index", "-i", type=int, required=True, help="Sample index in the store.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Output .npz file.")
@friendly_errors
def dump(store: Path, index: int, out: Path) -> None:
    """Write one sample as plain numpy arrays (.npz, no pickles).

    Keys: images (6,H,W,3) uint8 RGB; K; T_ego_from_cam; T_keyego_from_cam; T_ego_from_lidar;
    T_global_from_keyego; T_global_from_ego_cam; depth_uvd_0..5 (u, v, depth); semantics,
    mask_lidar, mask_camera, bev (18,200,200) when labelled; visibility_camera/lidar when computed;
    prev_index, prev_valid; token; timestamp; camera_order.
    """
    from occdata.store.inspect import dump_sample
    from occdata.store.reader import open_store

    keys = dump_sample(open_store(store), index, out)
    click.echo(f"{out}: {', '.join(keys)}")


@main.command("check-projection")
@_store_opt
@click.option("--index", "-i", type=int, default=0, show_default=True, help="Sample index in the store.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Output .png file.")
@friendly_errors
def check_projection(store: Path, index: int, out: Path) -> None:
    """Draw the stored LiDAR depth targets on the 6 images (coloured by depth) into one PNG."""
    from occdata.store.draw import draw_projection
    from occdata.store.reader import open_store

    click.echo(str(draw_projection(open_store(store), index, out)))


if __name__ == "__main__":
    main()
