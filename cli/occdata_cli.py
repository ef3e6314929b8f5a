"""`occdata`: turn nuScenes-format data (+ Occ3D labels) into one chunked zarr store (no torch)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import click
import numpy as np

from cli._common import DEFAULT_STORE, debug_option, exit_on_interrupt, friendly_errors, local_path, stop_on_sigterm
from cli.options import (
    JSON_UNITS,
    cluster_options,
    config_choice,
    grid_range_option,
    json_option,
    progress_option,
    removed_option,
    renamed_option,
    rig_options,
    root_options,
    split_option,
    split_source_options,
    splits_option,
    store_option,
    store_split,
)
from occdata.formats.gridspec import GRID_NAMES, GridSpec, grids_from_options
from occdata.text import plural

if TYPE_CHECKING:
    from occdata.labels.paint import ImageMasks
    from occdata.nuscenes.rig import RigChoice
    from occdata.nuscenes.splits import SplitChoice
    from occdata.runtime.cluster import ClusterConfig

__all__ = ["main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"], "show_default": True})
@debug_option
@click.version_option(package_name="fastocc")
def main() -> None:
    """occdata: nuScenes-format data and Occ3D labels -> one chunked zarr store.

    Every sub-command has its own --help.
    """


@main.command()
@click.option("--out", required=True, metavar="DIR",
              help="Output directory (nuScenes-format root; a folder or a file:// URL).")
@click.option("--scenes", default=2, show_default=True, type=click.IntRange(min=1), help="Number of scenes.")
@click.option("--samples", default=10, show_default=True, type=click.IntRange(min=1),
              help="Keyframes (2 Hz) per scene.")
@click.option("--seed", default=0, show_default=True, type=int, help="World seed (same seed, same bytes).")
@click.option("--rig", "rig_name", type=click.Choice(["nuscenes", "lyft", "truckscenes"]), default="nuscenes",
              show_default=True,
              help="Whose sensor rig, rates, file layout and table quirks to write: nuscenes (6 cameras, LIDAR_TOP "
                   "20 Hz), lyft (7 cameras, 3 LiDARs, 5 Hz keyframes, train_data/), truckscenes (4 cameras, 6 "
                   "LiDARs at 10 Hz, .pcd files). See docs/synth.md.")
@click.option("--width", default=None, type=click.IntRange(min=16),
              help="Image width (every camera). Default: the rig's (1600, 1920, 1980).")
@click.option("--height", default=None, type=click.IntRange(min=16),
              help="Image height (every camera). Default: the rig's (900, 1080, 943).")
@click.option("--table-only-scenes", default=0, show_default=True, type=click.IntRange(min=0), metavar="N",
              help="Also write N scenes as table rows alone (no sensor files or labels; split table_only): a "
                   "nuScenes-size tree for memory and start-up measurements.")
@click.option("--table-only-samples", default=40, show_default=True, type=click.IntRange(min=1), metavar="M",
              help="Keyframes per table-only scene (nuScenes has about 40).")
@click.option("--grid", "grids", multiple=True, type=click.Choice(list(GRID_NAMES)),
              help="Also write the truth on a benchmark's grid, in its frame and layout, under gts/<grid>/ "
                   "(repeatable; occ3d's truth is always gts/ itself). As `occdata labels --grid`.")
@click.option("--voxel-size", type=click.FloatRange(0.05, 2.0), default=None,
              help="Also write the truth on a custom Occ3D-style grid of this voxel size (m), in gts/occ3d-<size>m/.")
@grid_range_option()
@click.option("--uncompensated", is_flag=True,
              help="The LiDARs spin over one period, each point taken from the ego pose of its own time and "
                   "stamped with it (.pcd rigs: --rig truckscenes): clouds not motion-compensated, as `occdata "
                   "labels --deskew` corrects.")
@click.option("--image-masks", "image_masks", is_flag=False, flag_value="", default=None, metavar="[DIR]",
              help="Also write each camera image's truth class ids (Occ3D ids, 255 = sky) as a PNG at its path "
                   "under DIR (default OUT/masks: samples/CAM_FRONT/x.jpg -> OUT/masks/samples/CAM_FRONT/x.png): "
                   "the input of `occdata labels --image-masks DIR`.")
@progress_option()
@friendly_errors
def synth(out: str, scenes: int, samples: int, seed: int, rig_name: str, width: int | None, height: int | None,
          table_only_scenes: int, table_only_samples: int, grids: tuple[str, ...], voxel_size: float | None,
          grid_range: tuple[float, ...] | None, uncompensated: bool, image_masks: str | None,
          progress: bool) -> None:
    """Write a synthetic nuScenes-format world with Occ3D labels and exact depth maps.

    nuscenes rig: tables (v1.0-mini), 6 ray-cast camera images, a 32-beam LiDAR sweep per keyframe
    and 9 LiDAR sweeps (20 Hz) between keyframes under sweeps/LIDAR_TOP; --rig lyft / truckscenes:
    their rigs, rates, layouts and formats. Always gts/<scene>/<sample>/labels.npz and
    depth/<sample_data_token>.npy; with --grid / --voxel-size, the truth on other benchmarks'
    grids too. See docs/synth.md.
    """
    from occdata.synth import SynthConfig, synthesize

    specs = grids_from_options(grids, voxel_size, grid_range)
    root = synthesize(SynthConfig(out=local_path(out, "--out"), scenes=scenes, samples=samples, seed=seed,
                                  width=width, height=height, progress=progress,
                                  table_only_scenes=table_only_scenes, table_only_samples=table_only_samples,
                                  grids=specs, rig=rig_name, uncompensated=uncompensated,
                                  image_masks=None if image_masks is None else
                                  local_path(image_masks or str(Path(out) / "masks"), "--image-masks")))
    extra = f" (+ {table_only_scenes} table-only scenes)" if table_only_scenes else ""
    click.echo(f"wrote {plural(scenes, 'scene')} x {plural(samples, 'sample')}{extra} to {root}")


@main.command()
@root_options()
@click.option("--check-files/--no-check-files", default=True, show_default=True,
              help="Check that every keyframe image and LiDAR file exists.")
@json_option("Print the summary as JSON.")
@rig_options()
@split_source_options()
@friendly_errors
def scan(root: str, version: str | None, check_files: bool, as_json: bool, rig: RigChoice,
         scene_splits: SplitChoice) -> None:
    """Read and validate a nuScenes-format tree; print scenes and samples per split.

    Every foreign key is resolved and every sample is checked as `occdata build` checks it from
    the tables (values, paths inside the root, calibration, intrinsics); a broken tree fails with
    one line naming the file, row or token. The LIDAR_TOP sweep chains (prev links) are followed
    too and the sweeps between keyframes reported (their files are counted, not required).
    """
    from occdata.nuscenes.rig import describe_rig
    from occdata.nuscenes.summary import scan_tree

    summary = scan_tree(local_path(root, "--root"), version, check_files, rig, scene_splits)
    for note in summary["warnings"]:
        click.echo(f"warning: {note}", err=True)
    if as_json:
        click.echo(json.dumps(summary, indent=2))
        return
    click.echo(f"{summary['root']} [{summary['version']}]: {plural(summary['scenes'], 'scene')}, "
               f"{plural(summary['samples'], 'sample')}")
    click.echo(f"  rig: {describe_rig(summary['rig'])}")
    for line in summary["left_out"]:
        click.echo(f"  left out: {line}")
    for split, n in summary["samples_per_split"].items():
        n_scenes = summary["scenes_per_split"][split]
        click.echo(f"  {split:>12}: {n_scenes:5d} {'scene ' if n_scenes == 1 else 'scenes'} {n:7d} "
                   f"{'sample' if n == 1 else 'samples'}")
    sw = summary["sweeps"]
    files = f"; {sw['files_present']} of their files present" if "files_present" in sw else ""
    click.echo(f"  {summary['rig']['reference_lidar']} sweeps between keyframes: "
               f"{sw['per_keyframe_mean']:.2f} per keyframe "
               f"(min {sw['per_keyframe_min']}, max {sw['per_keyframe_max']}), {sw['total']} in all{files}")


@main.command()
@root_options()
@click.option("--out", default=DEFAULT_STORE, show_default=True, metavar="STORE",
              help="Output zarr store: a folder, or an fsspec URL (s3://bucket/data.zarr; needs occdata[s3]).")
@click.option("--gts", default=None, metavar="DIR",
              help="Occ3D-nuScenes labels folder: <gts>/<scene>/<sample_token>/labels.npz or the flat "
                   "<gts>/<sample_token>/labels.npz. Default: <root>/gts if it exists. Samples without a "
                   "label file are stored without labels (e.g. the test split); an explicit --gts in "
                   "which no sample finds its file is an error. An OpenOcc v2 tree (files with 'flow', e.g. "
                   "`occdata labels --grid openocc-v2` output) is read in its class ids and its flow is stored "
                   "(labels/flow); a tree must hold one format.")
@click.option("--gts-grid", "grid_name", type=click.Choice(list(GRID_NAMES)), default=None,
              help="The one grid of the --gts labels, in its benchmark's layout (e.g. gts/surroundocc/ from "
                   "`occdata labels|synth --grid surroundocc`): the store's label arrays get its shape, "
                   "in our 18 Occ3D class ids. Default: Occ3D's grid.")
@click.option("--voxel-size", type=click.FloatRange(0.05, 2.0), default=None,
              help="The --gts labels are a custom Occ3D-style grid of this voxel size (m), e.g. gts/occ3d-0.8m/.")
@renamed_option("--grid", "--gts-grid", "grid_name", type=click.Choice(list(GRID_NAMES)))
@grid_range_option("That custom grid's")
@splits_option("Keep only scenes of this split (repeatable)")
@cluster_options()
@click.option("--resume", is_flag=True, help="Continue an interrupted build of the same inputs and options.")
@click.option("--on-error", type=config_choice("occdata.store.build:BuildConfig.on_error"), default="fail",
              show_default=True,
              help="fail: stop at the first bad sample (everything before it stays committed); "
                   "skip: record the error in the store and go on.")
@click.option("--block-samples", type=int, default=32, show_default=True,
              help="Samples per shard (the unit of writing).")
@click.option("--image-scale", type=float, default=1.0, show_default=True,
              help="1.0 stores the original JPEG bytes; < 1 re-encodes the images at that scale.")
@click.option("--jpeg-quality", type=click.IntRange(1, 100), default=90, show_default=True,
              help="Quality (1-100) when re-encoding.")
@click.option("--lidar-sweeps", type=click.IntRange(0, 100), default=0, show_default=True, metavar="N",
              help="Depth targets from the keyframe LiDAR sweep plus up to N previous sweeps (20 Hz, "
                   "motion-compensated to each camera; needs the sweeps/ files). 0: the keyframe alone.")
@rig_options()
@split_source_options()
@progress_option()
@friendly_errors
def build(root: str, version: str | None, out: str, gts: str | None, grid_name: str | None,
          voxel_size: float | None, grid_range: tuple[float, ...] | None, splits: tuple[str, ...],
          cluster: ClusterConfig, resume: bool, on_error: str, block_samples: int, image_scale: float,
          jpeg_quality: int, lidar_sweeps: int, progress: bool, rig: RigChoice, scene_splits: SplitChoice) -> None:
    """Convert a nuScenes-format tree (+ Occ3D labels) into one chunked zarr store.

    Stores per keyframe: the rig's camera images (every camera of the tables unless --cameras),
    calibrations and poses, depth targets from every LiDAR,
    Occ3D labels and BEV multi-hot GT when labels exist, and 16-frame temporal indices.
    Kill it at any time and rerun with --resume: the result is identical.
    """
    from occdata.runtime.storage import is_remote
    from occdata.store.build import ROOT_GTS, BuildConfig, build_store
    from occdata.store.sample import SampleOptions

    out_path = out if is_remote(out) else local_path(out, "--out")
    config = BuildConfig(
        root=local_path(root, "--root"), out=out_path, version=version,
        gts=local_path(gts, "--gts") if gts is not None else ROOT_GTS, splits=splits, cluster=cluster,
        resume=resume, on_error=on_error,  # type: ignore[arg-type]
        block_samples=block_samples, options=SampleOptions(image_scale=image_scale, jpeg_quality=jpeg_quality,
                                                             lidar_sweeps=lidar_sweeps),
        progress=progress, grid=_one_grid(grid_name, voxel_size, grid_range), rig=rig, scene_splits=scene_splits,
    )
    click.echo(config.labels().note)
    with exit_on_interrupt(f"interrupted: every sample committed so far is kept in {out_path}; rerun the same "
                           "command with --resume to continue"):
        report = build_store(config)
    for note in report.warnings:
        click.echo(f"warning: {note}", err=True)
    click.echo(f"rig: {report.rig.describe()}")
    for line in report.rig.left_out:
        click.echo(f"left out: {line}")
    click.echo(
        f"{report.store}: {report.n_done}/{plural(report.n_samples, 'sample')} done, "
        f"{plural(report.n_errors, 'error')}, "
        f"{report.n_labelled} labelled ({report.processed_now} processed in this run)"
        + ("; OpenOcc v2 labels: classes mapped to Occ3D ids, flow stored in labels/flow" if report.flow else "")
        + (f"; labels on grid {config.grid.name} {config.grid.shape}, in Occ3D ids (occdata info shows the grid)"
           if config.grid is not None and config.grid.name not in ("occ3d", "openocc-v2") else "")
    )
    if report.n_errors:
        click.echo("errors are recorded in the store: see `occdata info --store ...`", err=True)


@main.command()
@root_options()
@click.option("--out", required=True, metavar="DIR",
              help="Output folder: <out>/<scene>/<sample_token>/labels.npz (Occ3D's layout), other grids in "
                   "<out>/<grid>/, and the manifest labels.json.")
@splits_option()
@click.option("--scene", "scenes", multiple=True, help="Only this scene (repeatable), e.g. scene-0916.")
@click.option("--all-sweeps", "all_sweeps", is_flag=True,
              help="Also aggregate the non-keyframe LiDAR sweeps (needs the sweeps/ files): denser labels.")
@renamed_option("--lidar-sweeps", "--all-sweeps", "all_sweeps", is_flag=True)
@click.option("--static-class", type=click.IntRange(0, 16), default=0, show_default=True,
              help="Without lidarseg only: the Occ3D class given to every point outside a box (0 = others, "
                   "i.e. 'occupied, not an annotated object'). Recorded in labels.json.")
@click.option("--ground-class", type=click.IntRange(0, 16), default=11, show_default=True,
              help="Without lidarseg only: the Occ3D class of static points on the scene's ground, found from "
                   "geometry (11 = driveable_surface, a stand-in for any flat ground). Equal to --static-class: "
                   "the ground is not split off. Recorded in labels.json.")
@click.option("--image-masks", "image_masks", default=None, metavar="DIR",
              help="Classes from your own 2D masks where there is no lidarseg: one PNG of class ids per camera "
                   "image at the image's path under DIR (samples/CAM_FRONT/x.jpg -> DIR/samples/CAM_FRONT/x.png); "
                   "each LiDAR point takes the class of the pixel it projects to where it is the visible surface.")
@click.option("--mask-classes", "mask_classes", default=None, metavar="FILE",
              help="With --image-masks: a JSON object mapping your segmenter's ids to Occ3D class names or "
                   "'ignore', e.g. {\"0\": \"driveable_surface\", \"13\": \"car\"}. Default: the ids are Occ3D's.")
@click.option("--knn-radius", type=click.FloatRange(0.01, 5.0), default=0.5, show_default=True,
              help="Metres within which a sweep point takes the class of the nearest labelled keyframe point.")
@click.option("--boxes", "boxes_mode", type=click.Choice(["auto", "none"]), default="auto", show_default=True,
              help="auto: boxes where a scene has them, carving where it has none. none: withhold the boxes and "
                   "split points into static and dynamic by the scene's own rays (free-space carving); with "
                   "--no-carve, every point static in the global frame (the naive control: moving objects smear).")
@removed_option("--no-boxes", "--boxes none --no-carve (the naive control; --boxes none alone carves)")
@click.option("--carve/--no-carve", default=None,
              help="Carve on top of the boxes too (movers the annotators missed), or never carve. Default: carve "
                   "exactly the scenes without boxes (docs/labels.md, 'Without boxes').")
@click.option("--dynamic-class", type=click.IntRange(0, 16), default=4, show_default=True,
              help="Without lidarseg, the Occ3D class of points found dynamic by carving (4 = car, a stand-in for "
                   "'something that moved'). Recorded in labels.json.")
@click.option("--deskew", is_flag=True,
              help="Place each LiDAR point by the ego pose of its own time where the point file has per-point "
                   "times (.pcd 'timestamp'), for clouds not motion-compensated already (docs/rigs.md).")
@click.option("--densify", is_flag=True,
              help="Fill what surfaces imply where no LiDAR ray saw free space: objects' boxes, a few voxels "
                   "behind buildings and vegetation, holes in surfaces (docs/labels.md, 'Densification').")
@click.option("--grid", "grids", multiple=True, type=click.Choice(list(GRID_NAMES)),
              help="A benchmark's grid to write (repeatable; one aggregation serves all): occ3d (default; 0.4 m, "
                   "key ego, OUT/<scene>/<token>/labels.npz), openocc-v2 (its classes + flow), surroundocc (0.5 m, "
                   "LiDAR frame, sparse .npy), openoccupancy (0.2 m, 512x512x40, LiDAR frame). Grids other than "
                   "occ3d go to OUT/<grid>/ in their benchmark's own layout.")
@click.option("--voxel-size", type=click.FloatRange(0.05, 2.0), default=None,
              help="Also write a custom grid: Occ3D's frame, classes and layout at this voxel size (m), in "
                   "OUT/occ3d-<size>m/.")
@grid_range_option()
@rig_options()
@split_source_options()
@cluster_options(per_worker=", one scene each at a time")
@click.option("--resume", is_flag=True, help="Continue an interrupted run: finished scenes are skipped.")
@progress_option()
@friendly_errors
def labels(root: str, version: str | None, out: str, splits: tuple[str, ...], scenes: tuple[str, ...],
           all_sweeps: bool, static_class: int, ground_class: int, image_masks: str | None, mask_classes: str | None,
           knn_radius: float, boxes_mode: str,
           carve: bool | None, dynamic_class: int, deskew: bool, densify: bool,
           grids: tuple[str, ...],
           voxel_size: float | None, grid_range: tuple[float, ...] | None, rig: RigChoice,
           scene_splits: SplitChoice, cluster: ClusterConfig, resume: bool, progress: bool) -> None:
    """Generate occupancy labels from LiDAR and 3D boxes (and lidarseg when present), on the grid of
    Occ3D-nuScenes and, with --grid / --voxel-size, of other benchmarks; without boxes (or with --boxes
    none), moving objects are found by free-space carving.

    Per scene: LiDAR points aggregated over time, static points in the global frame, points inside a
    box in that box's frame (moving objects stay sharp); then per keyframe and grid a majority vote of
    point classes per voxel, and LiDAR and camera visibility masks where the layout has them. The
    Occ3D output is read by `occdata build --gts OUT`. See docs/labels.md.
    """
    from occdata.labels import LabelOptions, LabelsConfig, generate_labels

    out_path = local_path(out, "--out")
    specs = grids_from_options(grids, voxel_size, grid_range)
    masks = _image_masks(image_masks, mask_classes)
    with exit_on_interrupt(f"interrupted: finished scenes are kept in {out_path}; rerun with --resume to continue"):
        report = generate_labels(LabelsConfig(
            root=local_path(root, "--root"), out=out_path, version=version, splits=splits or None,
            scenes=scenes or None, resume=resume, progress=progress,
            options=LabelOptions(all_sweeps=all_sweeps, static_class=static_class, knn_radius=knn_radius,
                                 use_boxes=boxes_mode == "auto", densify=densify,
                                 carve=carve if carve is not None else (True if boxes_mode == "none" else None),
                                 dynamic_class=dynamic_class, deskew=deskew, ground_class=ground_class,
                                 image_masks=masks),
            cluster=cluster, grids=specs, rig=rig, scene_splits=scene_splits,
        ))
    seg = "lidarseg classes" if report.with_lidarseg else (
        f"no lidarseg: static points are class {static_class}"
        + (f", on the ground {ground_class}" if ground_class != static_class else "")
        + ("; classes from the image masks where they see a point" if masks is not None else ""))
    carved = sorted(name for name, mode in report.modes.items() if "carve" in mode)
    if carved and len(carved) < len(report.modes):
        click.echo(f"carved (no boxes, or --carve): {len(carved)} of {len(report.modes)} scenes: "
                   f"{', '.join(carved[:5])}{' ...' if len(carved) > 5 else ''}", err=True)
    click.echo(f"{out_path}: {plural(report.scenes_done, 'scene')} labelled, {report.scenes_skipped} already done, "
               f"{plural(report.keyframes, 'keyframe')} ({seg}"
               f"{'; moving objects by free-space carving' if carved else ''}); manifest {report.manifest}")


def _image_masks(folder: str | None, classes: str | None) -> ImageMasks | None:
    """`--image-masks DIR` and `--mask-classes FILE` as `occdata.labels.paint.ImageMasks` (None: no masks)."""
    from occdata.formats.imagemasks import MaskClasses, load_mask_classes
    from occdata.labels.paint import ImageMasks

    if folder is None:
        if classes is not None:
            raise click.UsageError("--mask-classes needs --image-masks")
        return None
    root = local_path(folder, "--image-masks")
    if not root.is_dir():
        raise click.UsageError(f"--image-masks {folder}: not a folder")
    table = load_mask_classes(local_path(classes, "--mask-classes")) if classes else MaskClasses.occ3d()
    return ImageMasks(root, table)


@main.command("bev-gt")
@store_option()
@progress_option()
@friendly_errors
def bev_gt(store: str, progress: bool) -> None:
    """(Re)compute the BEV multi-hot ground truth from the stored voxel labels.

    One uint32 bit field per BEV cell (bit c: class c occurs in the column; bit 17 = free).
    `occdata build` already runs this when labels exist.
    """
    from occdata.store.commands.bev_gt import compute_bev_gt
    from occdata.store.reader import open_store

    open_store(store)  # validates the schema first
    n = compute_bev_gt(store, progress=progress)
    click.echo(f"{store}: BEV GT written for {plural(n, 'labelled sample')}")


@main.command()
@store_option()
@click.option("--recompute", is_flag=True,
              help="Recompute for every labelled sample (default: only those without a shipped camera mask), "
                   "and print the agreement with the shipped masks per class.")
@click.option("--lidar-sweeps", type=click.IntRange(0, 100), default=None, metavar="N",
              help="LiDAR rays from the source tree instead of the stored depth targets: every point of the "
                   "keyframe sweep and of up to N previous sweeps (Occ3D aggregates sweeps).")
@click.option("--root", default=None, metavar="DIR",
              help="With --lidar-sweeps: the nuScenes-format tree (default: the store's source root).")
@progress_option()
@friendly_errors
def visibility(store: str, recompute: bool, lidar_sweeps: int | None, root: str | None, progress: bool) -> None:
    """Occ3D-style camera and LiDAR masks from the stored semantics (docs/visibility.md).

    LiDAR mask: voxels the stored keyframe LiDAR rays pass through or end in, plus every object
    voxel (as Occ3D's). Camera mask, within the label's LiDAR mask (the computed one if the label
    ships none): LiDAR-observed free and ground voxels, and object voxels whose centre some camera
    sees with at most 7 object voxels before it on the ray. Stored as visibility/camera and
    visibility/lidar; only labelled samples are processed.
    """
    from occdata.store.commands.visibility import compute_visibility

    report = compute_visibility(store, recompute=recompute, progress=progress, lidar_sweeps=lidar_sweeps,
                                root=local_path(root, "--root") if root is not None else None)
    click.echo(f"{store}: visibility computed for {plural(report.computed, 'sample')} "
               f"({report.seconds_per_sample:.2f} s/sample); {report.skipped_unlabelled} unlabelled skipped")
    if report.computed:
        click.echo(f"  LiDAR mask: {100 * report.free_observed:.2f}% of free voxels observed")
    if report.compared:
        from occdata.constants import CLASS_NAMES, FREE_LABEL

        occ = np.arange(len(CLASS_NAMES)) != FREE_LABEL
        click.echo(f"agreement with the shipped masks over {plural(report.compared, 'sample')} (IoU of visible sets; "
                   "visible % of each class's voxels):")
        for name, c in (("mask_camera", report.camera), ("mask_lidar", report.lidar)):
            click.echo(f"  {name}: IoU all {c.iou():.4f}, occupied {c.iou(occ):.4f}, free {c.iou(~occ):.4f}")
        click.echo(f"  {'class':20s} {'voxels':>10s} {'camera ours':>11s} {'shipped':>8s} {'IoU':>6s}"
                   f" {'lidar ours':>10s} {'shipped':>8s} {'IoU':>6s}")
        cam, lid = report.camera, report.lidar
        for k, name in enumerate(CLASS_NAMES):
            n = cam.voxels[k]
            if not n:
                continue
            click.echo(f"  {name:20s} {n:10d} {100 * cam.computed[k] / n:10.1f}% {100 * cam.shipped[k] / n:7.1f}%"
                       f" {cam.iou([k]):6.3f} {100 * lid.computed[k] / n:9.1f}% {100 * lid.shipped[k] / n:7.1f}%"
                       f" {lid.iou([k]):6.3f}")


@main.command("visibility-check")
@click.option("--label", required=True, metavar="FILE", help="An Occ3D labels.npz (a path or a file:// URL).")
@root_options("nuScenes-format root whose camera rig to use (cameras are rigid on the car; a folder or a "
              "file:// URL).")
@click.option("--sample", default=None, help="Sample token whose cameras to use (default: the first keyframe).")
@click.option("--max-occluders", default=7, show_default=True, type=click.IntRange(min=0),
              help="Object voxels a camera ray may cross before a voxel stops being visible (0 = strict).")
@json_option(f"Print the figures as JSON ({JSON_UNITS}).")
@friendly_errors
def visibility_check(label: str, root: str, version: str | None, sample: str | None, max_occluders: int,
                     as_json: bool) -> None:
    """Recompute one Occ3D label's camera mask from its semantics + mask_lidar and score it.

    Prints the IoU with the label's mask_camera (all / occupied / free voxels) and each class's
    visible fraction, ours beside the label's. See docs/visibility.md.
    """
    from occdata.constants import CLASS_NAMES
    from occdata.visibility.check import CheckConfig, check_label

    r = check_label(CheckConfig(label=local_path(label, "--label"), root=local_path(root, "--root"), version=version,
                                sample=sample, max_occluders=max_occluders))
    if as_json:
        click.echo(json.dumps({
            "unit": "percent", "iou_all": _percent(r.iou_all), "iou_occupied": _percent(r.iou_occupied),
            "iou_free": _percent(r.iou_free), "precision": _percent(r.precision), "recall": _percent(r.recall),
            "visible": {CLASS_NAMES[k]: {"ours": _percent(a), "label": _percent(b), "voxels": n}
                        for k, (a, b, n) in r.visible_fraction.items()},
        }, indent=2))
        return
    click.echo(f"IoU with the label's mask_camera: all {r.iou_all:.4f}, occupied {r.iou_occupied:.4f}, "
               f"free {r.iou_free:.4f} (precision {r.precision:.4f}, recall {r.recall:.4f})")
    click.echo(f"  {'class':20s} {'voxels':>8s} {'ours':>7s} {'label':>7s}")
    for k, (a, b, n) in r.visible_fraction.items():
        click.echo(f"  {CLASS_NAMES[k]:20s} {n:8d} {100 * a:6.1f}% {100 * b:6.1f}%")


def _one_grid(name: str | None, voxel_size: float | None, grid_range: tuple[float, ...] | None) -> GridSpec | None:
    """`occdata build`'s labels grid: None (Occ3D's) without options, else exactly one grid."""
    if name is None and voxel_size is None and grid_range is None:
        return None
    if name is not None and (voxel_size is not None or grid_range is not None):
        raise click.UsageError("give either --gts-grid or --voxel-size/--range (one labels grid), not both")
    (spec,) = grids_from_options(() if name is None else (name,), voxel_size, grid_range)
    return spec


@main.command()
@store_option()
@json_option("Print everything as JSON (scene table included).")
@friendly_errors
def info(store: str, as_json: bool) -> None:
    """Samples, scenes, arrays (shapes, dtypes, chunks), attrs and recorded errors of a store."""
    from occdata.nuscenes.rig import describe_rig
    from occdata.store.commands.info import store_info
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
    click.echo(f"  rig: {describe_rig(summary['rig'])}")
    click.echo(f"  images: {a['images']}")
    click.echo(f"  grid: {summary['grid']['line']}")
    click.echo("  flow: labels/flow, (vx, vy) m/s from OpenOcc v2 labels (schema v3)" if summary["flow"] else
               "  flow: none (labels without flow)")
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
@store_option()
@progress_option()
@click.option("--images", is_flag=True, help="Also decode every stored image and report damaged JPEGs.")
@cluster_options(", a few hundred samples each at a time")
@friendly_errors
def verify(store: str, progress: bool, images: bool, cluster: ClusterConfig) -> None:
    """Recompute every committed sample's checksums; report corruption with the sample it hits.

    The checksums run as tasks of a few hundred samples, in this process or on Dask (--workers,
    --scheduler: the workers must reach --store at the same path); the report is the same. With
    --images, also decode every stored image and report those that libjpeg decodes only with a
    warning (damage that a store built before that check at build time may hold). Exits 1 if
    anything is wrong.
    """
    from tqdm import tqdm

    from occdata.runtime.cluster import cluster_client
    from occdata.store.commands.verify import pending_samples, verify_store
    from occdata.store.reader import open_store

    reader = open_store(store)
    with exit_on_interrupt("interrupted: verify stopped before it finished; nothing was changed"), \
            cluster_client(cluster) as client, \
            tqdm(total=reader.n_samples, desc="verify", unit="sample", disable=not progress) as bar:
        problems = verify_store(reader, progress=bar.update, client=client)
    pending = pending_samples(reader)
    if images:
        from occdata.store.commands.verify_images import verify_images

        with tqdm(total=len(reader.done_indices()), desc="images", unit="sample", disable=not progress) as bar:
            problems += verify_images(reader, progress=bar.update)
    if problems:
        for p in problems:
            click.echo(f"CORRUPT sample {p.index} ({p.token}): {p.array}: {p.reason}")
    if len(pending):
        click.echo(f"PENDING {len(pending)} of {reader.n_samples} samples not built yet (first: {int(pending[0])}, "
                   f"last: {int(pending[-1])}): the build was interrupted or is running; finish it with "
                   "`occdata build ... --resume`")
    if problems or len(pending):
        what = [plural(len(problems), "problem")] if problems else []
        what += [f"{len(pending)} pending sample(s)"] if len(pending) else []
        raise click.ClickException(f"{' and '.join(what)} in {store}")
    click.echo(f"{store}: all {plural(int((reader.state != 0).sum()), 'committed sample')} verified")


@main.command()
@store_option()
@click.option("--train-split", default="train", show_default=True, metavar="SPLIT",
              help="Dataset split whose labels are counted.")
@split_option(help="Dataset split to score.")
@json_option(f"Print the results as JSON ({JSON_UNITS}).")
@friendly_errors
def baseline(store: str, train_split: str, split: str | None, as_json: bool) -> None:
    """Score the image-free baseline: every voxel's most frequent training label.

    The floor a camera model must beat (it knows the average street, not the scene). mIoU with the
    camera mask, as `occdata eval` reports it.
    """
    from occdata.constants import CLASS_NAMES
    from occdata.eval.baseline import image_free_baseline
    from occdata.store.reader import open_store

    split = store_split(store, split)
    r = image_free_baseline(open_store(store), train_split, split)
    if as_json:  # NaN (class absent from truth and prediction) -> null
        click.echo(json.dumps({
            "unit": "percent", "train_split": train_split, "split": split, "train_samples": r.train_samples,
            "samples": r.samples, "miou_camera_mask": _percent(r.miou_camera_mask),
            "miou_no_mask": _percent(r.miou_no_mask),
            "per_class_iou_camera_mask": {name: _percent(x) for name, x in
                                          zip(CLASS_NAMES, r.per_class_iou_camera_mask, strict=False)},
        }))
        return
    click.echo(f"image-free baseline ({r.train_samples} {train_split} -> {plural(r.samples, f'{split} sample')}): "
               f"mIoU {100 * r.miou_camera_mask:.2f}% (camera mask), {100 * r.miou_no_mask:.2f}% (no mask)")


def _percent(fraction: float) -> float | None:
    """A fraction as JSON percent (4 decimals, as `occdata eval --json`); NaN (0/0) -> null."""
    return None if np.isnan(fraction) else round(100.0 * float(fraction), 4)


@main.command("eval")
@click.option("--pred", required=True, metavar="DIR",
              help="Predictions: <scene>/<token>/labels.npz (key 'semantics', the Occ3D layout) or <token>.npz "
                   "(key 'semantics' or 'pred'); uint8 (200, 200, 16), 17 = free; optional 'flow' (200, 200, "
                   "16, 2) float (vx, vy) m/s for mAVE / OccScore.")
@click.option("--pred-classes", type=click.Choice(["occ3d", "openocc-v2"]), default="occ3d", show_default=True,
              help="The predictions' label ids: occ3d (17 = free) or openocc-v2 (OpenOcc v2's order, 16 = free; "
                   "e.g. `occdata labels --grid openocc-v2` output).")
@store_option(help="The occdata store holding the ground truth and poses (a folder or an fsspec URL).")
@split_option(help="Dataset split to score (every labelled sample of it).")
@click.option("--mask", type=config_choice("occdata.eval.evaluate:MaskName"), default="camera", show_default=True,
              help="Visibility mask for mIoU (Occ3D uses camera). RayIoU uses no mask.")
@click.option("--no-rayiou", is_flag=True, help="Skip RayIoU (mIoU only, much faster).")
@json_option(f"Print the results as JSON ({JSON_UNITS}; null = class absent).")
@progress_option()
@friendly_errors
def eval_cmd(pred: str, pred_classes: str, store: str, split: str | None, mask: str, no_rayiou: bool, as_json: bool,
             progress: bool) -> None:
    """Score saved predictions: Occ3D mIoU (+ geometry IoU) and RayIoU@1/2/4 m, on the CPU; and
    OpenOcc v2's mAVE and OccScore when the store has flow and the predictions carry it.

    mIoU: one confusion matrix over the split, voxels inside the mask, mean over the 17 semantic
    classes (classes absent from truth and prediction are skipped). RayIoU: the SparseOcc protocol
    (14,040 LiDAR-like rays from up to 8 origins of the sample's scene, first-hit class and
    distance). mAVE: mean over the 8 moving classes of the velocity error on the true-positive rays
    at 2 m; OccScore = 0.9 RayIoU + 0.1 max(1 - mAVE, 0). See docs/metrics.md.
    """
    from occdata.eval.evaluate import (
        EvalConfig,
        evaluate_predictions,
        flow_line,
        format_table,
        results_dict,
        summary_line,
    )

    split = store_split(store, split)
    report = evaluate_predictions(EvalConfig(pred=local_path(pred, "--pred"), store=store, split=split, mask=mask,  # type: ignore[arg-type]
                                             rayiou=not no_rayiou, progress=progress, pred_classes=pred_classes))
    if as_json:
        extra = {} if report.flow_note is None else {"mave": None, "occ_score": None, "flow_note": report.flow_note}
        extra |= {} if report.grid is None else {"grid": report.grid}
        click.echo(json.dumps(results_dict(report.miou, report.rayiou, split=report.split, mask=report.mask,
                                           n_samples=report.n_samples,
                                           unlabelled_skipped=report.n_unlabelled_skipped,
                                           seconds=round(report.seconds, 3), **extra), indent=2))
        return
    click.echo(format_table(report.miou, report.rayiou))
    if report.n_unlabelled_skipped:
        click.echo(f"({report.n_unlabelled_skipped} unlabelled '{split}' samples skipped)")
    click.echo(summary_line(report))
    if flow_line(report):
        click.echo(flow_line(report))


@main.command()
@store_option()
@click.option("--index", "-i", type=int, default=0, help="Sample index in the store.")
@click.option("--out", required=True, metavar="FILE", help="Output .npz file (a path or a file:// URL).")
@friendly_errors
def dump(store: str, index: int, out: str) -> None:
    """Write one sample as plain numpy arrays (.npz, no pickles).

    Keys: images (6,H,W,3) uint8 RGB; K; T_ego_from_cam; T_keyego_from_cam; T_ego_from_lidar;
    T_global_from_keyego; T_global_from_ego_cam; depth_uvd_0..5 (u, v, depth); semantics,
    mask_lidar, mask_camera, bev (18,200,200) when labelled; visibility_camera/lidar when computed;
    prev_index, prev_valid; token; timestamp; camera_order.
    """
    from occdata.store.commands.info import dump_sample
    from occdata.store.reader import open_store

    keys = dump_sample(open_store(store), index, local_path(out, "--out"))
    click.echo(f"{out}: {', '.join(keys)}")


@main.command("check-projection")
@store_option()
@click.option("--index", "-i", type=int, default=0, help="Sample index in the store.")
@click.option("--out", required=True, metavar="FILE", help="Output .png file (a path or a file:// URL).")
@friendly_errors
def check_projection(store: str, index: int, out: str) -> None:
    """Draw the stored LiDAR depth targets on the 6 images (coloured by depth) into one PNG."""
    from occdata.store.commands.check_projection import draw_projection
    from occdata.store.reader import open_store

    click.echo(str(draw_projection(open_store(store), index, local_path(out, "--out"))))


@main.command()
@store_option()
@click.option("--pred", default=None, metavar="DIR", help="Prediction folder (as `occdata eval --pred`).")
@click.option("--scene", default=None, help="Scene to show first (the one exported with --export).")
@split_option(help="Only the scenes of this dataset split; default: all", auto=False)
@click.option("--view", "view_name", type=config_choice("occdata.view.config:VIEWS"), default=None,
              help="Initial view (default: side with --pred, else label). speed: the labels coloured by "
                   "|flow| (stores with flow).")
@click.option("--mask", default="none", show_default=True, type=config_choice("occdata.view.config:MASK_CHOICES"),
              help="Voxels outside this mask are grey (camera: what mIoU scores).")
@click.option("--style", type=config_choice("occdata.view.config:STYLES"), default="flat", show_default=True,
              help="flat: exact class colours; cubes: lit boxes.")
@click.option("--lidar", is_flag=True, help="Also draw the stored LiDAR depth points in 3D.")
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to serve on (others expose the data).")
@click.option("--port", default=8080, show_default=True, type=int, help="Port (0: any free port; taken: the next).")
@click.option("--export", default=None, metavar="FILE.html", help="Write one scene as a self-contained HTML file.")
@friendly_errors
@stop_on_sigterm
def view(store: str, pred: str | None, scene: str | None, split: str | None, view_name: str | None, mask: str,
         style: str, lidar: bool, host: str, port: int, export: str | None) -> None:
    """The scene in 3D in a browser: labels, predictions, error view, masks, cameras, LiDAR (docs/view.md).

    Serves a local web viewer and prints its URL (Ctrl-C stops it); with --export, writes one scene
    as an HTML file that opens in any browser with no server. Needs `pip install 'fastocc[view]'`
    (in a clone: `pip install -e '.[view]'`).
    """
    from occdata.view import FrameOptions, ViewConfig, run_view

    name = view_name or ("side" if pred else "label")
    cfg = ViewConfig(store=store, pred=local_path(pred, "--pred") if pred else None, scene=scene, split=split,
                     host=host, port=port, export=Path(local_path(export, "--export")) if export else None,
                     frame=FrameOptions(view=name, mask=mask, style=style, lidar=lidar))  # type: ignore[arg-type]
    run_view(cfg, echo=lambda m: click.echo(m), warn=lambda m: click.echo(m, err=True))


if __name__ == "__main__":
    main()
