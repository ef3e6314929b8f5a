"""benchmarks.ablations: the rows are valid training configs that differ from the recipe only where the
ablation says; the history rows train scene-sequentially; the tables apply "not resolved" by the seed
spread (hand-made numbers); status prints at most two background lanes."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks import ablations as ab
from fastocc.train.config import TrainConfig, flat_config, load_config
from fastocc.train.setup import trains_sequentially

REPO = Path(__file__).resolve().parents[1]
RECIPE = load_config(REPO / "benchmarks" / "configs" / "learn_nano_18ep.toml")


def _changed(cfg: TrainConfig) -> dict[str, object]:
    base, now = flat_config(RECIPE.to_dict()), flat_config(cfg.to_dict())
    return {k: now[k] for k in now if now[k] != base[k]}


def _key(name: str) -> str:
    """A row override's name as `flat_config` spells it (legacy `w_bev` -> `loss.bev`)."""
    return f"loss.{name[2:]}" if name.startswith("w_") else name


@pytest.mark.parametrize("row", sorted(ab.ROWS))
def test_rows_are_valid_configs_differing_only_where_intended(row: str) -> None:
    cfg = ab.row_config(row, seed=1, epochs=5)
    model = cfg.model_config()  # builds: head, history and switch are valid together
    changed = _changed(cfg)
    assert changed.pop("epochs") == 5 and changed.pop("seed") == 1 and changed.pop("keep_epochs") == 5
    assert changed.pop("out") == f"runs/ablate/{row}-s1"
    base = flat_config(RECIPE.to_dict())
    intended = {_key(k): list(v) if isinstance(v, tuple) else v for k, v in ab.ROWS[row].overrides
                if v != base[_key(k)]}
    assert changed == intended
    assert model.name == "nano" and model.input_hw == dict(ab.ROWS[row].overrides).get("input_hw", (96, 256))


def test_component_rows_switch_what_the_paper_switches() -> None:
    rows = {r: ab.row_config(r, 0, 3) for r in ("fastocc", "neither", "bev-only", "interp-only")}
    assert [(c.model_config().interp_features, c.loss.bev > 0) for c in rows.values()] == [
        (True, True), (False, False), (False, True), (True, False)]
    assert [ab.row_config(r, 0, 3).head for r in ("deconv", "3dfcn", "fastocc")] == ["deconv", "3dfcn", "fastocc"]


def test_issue_26_rows() -> None:
    """bev-unfold: the paper's BEV-only reading; hist0fuse: the fusion-layer control; hist16cached: the cached
    queue; nano128: Table III's second input size."""
    m = {r: ab.row_config(r, 0, 3).model_config() for r in ("bev-unfold", "hist0fuse", "hist16cached", "nano128")}
    assert (m["bev-unfold"].interp_features, m["bev-unfold"].bev_height.value) == (False, "unfold")
    assert ab.row_config("bev-unfold", 0, 3).loss.bev > 0  # BEV supervision on, as in bev-only
    assert (m["hist0fuse"].num_history, m["hist0fuse"].has_temporal, m["hist0fuse"].temporal_fusion.value) == (
        0, True, "concat")  # the same fusion layer as hist16, without history
    assert (m["hist16cached"].num_history, m["hist16cached"].temporal_fusion.value) == (16, "cached")
    assert m["nano128"].input_hw == (128, 352)
    assert trains_sequentially(ab.row_config("hist0fuse", 0, 3))
    listed = {tr.row for t in ab.TABLES for tr in t.rows}
    assert {"bev-unfold", "hist0fuse", "hist16cached", "nano128"} <= listed


@pytest.mark.parametrize(("row", "history"), [("hist0", 0), ("hist0fuse", 0), ("hist4", 4), ("hist16", 16),
                                              ("hist16cached", 16)])
def test_history_rows_set_history_and_scene_sequential_order(row: str, history: int) -> None:
    cfg = ab.row_config(row, 0, 3)
    assert cfg.model_config().num_history == history
    assert trains_sequentially(cfg)  # the trainer walks scenes in order
    assert not trains_sequentially(ab.row_config("fastocc", 0, 3))  # control


def test_verdict_uses_the_larger_seed_spread() -> None:
    # means 0.31 vs 0.355 (gap 4.5 points), spreads 2 and 1 points: resolved
    assert ab.verdict([0.30, 0.32], [0.35, 0.36]) == "< by 4.50 (seed spread 2.00)"
    # gap 0.25 points < spread 2.5 points: not resolved
    assert ab.verdict([0.35, 0.36], [0.345, 0.37]).startswith("not resolved (|gap| 0.25 < seed spread 2.50)")
    # exact binary fractions: gap 0.25 == spread 0.25 is resolved (only a smaller gap is not)
    assert ab.verdict([0.25, 0.5], [0.625, 0.625]).startswith("< by 25.00")
    assert ab.verdict([0.25, 0.5], [0.6, 0.625]).startswith("not resolved")  # gap 0.2375 < 0.25
    assert ab.verdict([0.3], [0.2, 0.2]) == "pending"  # one seed missing


def _fake_results() -> dict:
    vals = {"deconv": (0.30, 0.32), "3dfcn": (0.35, 0.36), "fastocc": (0.345, 0.37), "bev-only": (0.20, 0.21),
            "interp-only": (0.34, 0.35)}
    runs = {}
    for row, (a, b) in vals.items():
        for seed, v in zip((0, 1), (a, b), strict=True):
            runs[f"{row}-s{seed}"] = {"row": row, "seed": seed, "miou": v, "rayiou": v / 2, "geo_iou": 0.5,
                                      "s_per_step": 0.7, "curve": [[240, v / 2], [480, v]]}
    latency = {"head_ms": {"fastocc": 100.0, "3dfcn": 250.0, "deconv": 150.0},
               "ratio_to_fastocc": {"fastocc": 1.0, "3dfcn": 2.5, "deconv": 1.5},
               "config": {"preset": "nano", "input_hw": [128, 352], "device_name": "cpu", "threads": 2, "repeats": 5},
               "loadavg_1min": 1.25, "command": "python -m benchmarks.ablations latency --preset nano --repeats 5"}
    return {"runs": runs, "latency": latency, "store": "w8v.zarr"}


def test_tables_markdown_from_hand_made_results() -> None:
    md = ab.render_markdown(_fake_results(), epochs=6)
    assert "**E = 6 epochs**" in md
    assert "| Baseline: 3D deconv head (`deconv`) | 38.44 | 306 (1.38) | 30.00 / 32.00 (mean 31.00) |" in md
    assert ("- `deconv` vs `3dfcn`: mIoU < by 4.50 (seed spread 2.00); RayIoU < by 2.25 (seed spread 1.00); "
            "paper < by 2.58: agrees") in md
    assert "- `3dfcn` vs `fastocc`: mIoU not resolved (|gap| 0.25 < seed spread 2.50)" in md
    assert md.count("paper > by 0.27: not resolved") == 1  # 3dfcn vs fastocc: the paper's order is not ranked
    assert "- `bev-only` vs `interp-only`: mIoU < by 14.00 (seed spread 1.00)" in md  # resolved, agrees
    assert "paper < by 1.41: agrees" in md
    assert "| neither (`neither`) | - | pending | pending | pending | pending |" in md  # no runs yet
    one_seed = _fake_results()
    del one_seed["runs"]["deconv-s1"]
    md1 = ab.render_markdown(one_seed, epochs=6)
    assert "| Baseline: 3D deconv head (`deconv`) | 38.44 | 306 (1.38) | 30.00 / pending | 15.00 / pending |" in md1
    assert "- `deconv` vs `3dfcn`: mIoU pending; RayIoU pending" in md1
    assert "- `neither` vs `bev-only`: mIoU pending; RayIoU pending" in md
    assert "| 2.50 |" in md  # 3D FCN head latency ratio
    assert "(nano 128x352, cpu, 2 threads, median of 5 x 1 rounds, 1-min load 1.2): fastocc 100 ms, 3dfcn 250 ms" in md
    assert "| 0 previous frames (`hist0`) | - | pending |" in md
    assert "python -m benchmarks.ablations run ROW --seed S --epochs 6" in md


def test_tables_command_writes_markdown_and_pngs(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    import json

    res = tmp_path / "ab.json"
    res.write_text(json.dumps(_fake_results()))
    ab.tables(res, tmp_path / "ab.md", epochs=6)
    assert (tmp_path / "ab.md").read_text() == ab.render_markdown(
        _fake_results(), 6, {"head": "img/ab_head.png", "components": "img/ab_components.png",
                             "resolution": "img/ab_resolution.png"})  # pictures beside the page, in img/
    img = tmp_path / "img"
    assert (img / "ab_head.png").stat().st_size > 1000 and not (img / "ab_history.png").exists()


def test_status_lanes_run_every_missing_run_once_two_at_a_time(tmp_path: Path) -> None:
    todo = [("fastocc", 0), ("fastocc", 1), ("3dfcn", 0)]
    cmds = ab.lane_commands(todo, 6, None, Path("runs/ablate"))
    assert len(cmds) == 2 and all(c.startswith("mkdir -p runs/ablate/logs && nohup bash -c ") for c in cmds)
    assert [c.endswith(f"> runs/ablate/logs/lane{k}.log 2>&1 &") for k, c in enumerate(cmds)] == [True, True]
    joined = " ".join(cmds)
    assert joined.count(" && python") == 0 and joined.count("; ") == 1  # a failed run does not stop its lane
    for row, seed in todo:
        assert joined.count(f"run {row} --seed {seed} --epochs 6 --threads 1") == 1
    assert ab.lane_commands(todo[:1], 6, None, Path("runs/ablate"))[0].count("--threads 2") == 1
    ab.status(6, None, tmp_path)  # nothing there: every run is missing, no error


def test_tables_keeps_hand_written_readings(tmp_path: Path) -> None:
    import json

    res, md = tmp_path / "ab.json", tmp_path / "ab.md"
    res.write_text(json.dumps({"runs": {}}))
    ab.tables(res, md, epochs=6)
    assert md.read_text().count(ab.READING_PENDING) == 5  # head, components, history, resolution, tta
    md.write_text(md.read_text().replace("<!-- reading:head -->\n" + ab.READING_PENDING,
                                         "<!-- reading:head -->\nOurs agrees.\nTwo lines."))
    ab.tables(res, md, epochs=6)
    text = md.read_text()
    assert "<!-- reading:head -->\nOurs agrees.\nTwo lines.\n<!-- /reading -->" in text
    assert text.count(ab.READING_PENDING) == 4
    res.write_text(json.dumps({"runs": {}, "epochs": 4}))
    with pytest.raises(SystemExit, match="E = 4"):
        ab.tables(res, md, epochs=6)


def test_cache_reuses_a_score_until_the_checkpoint_or_store_changes(tmp_path: Path) -> None:
    calls: list[int] = []

    def compute() -> dict[str, object]:
        calls.append(1)
        return {"miou": 0.1 * len(calls)}

    cache = tmp_path / "ablate_score.json"
    assert ab._cached(cache, 10, "a.zarr", compute)["miou"] == 0.1
    assert ab._cached(cache, 10, "a.zarr", compute)["miou"] == 0.1 and len(calls) == 1
    assert ab._cached(cache, 11, "a.zarr", compute)["miou"] == 0.2  # resumed run: new last.pt
    assert ab._cached(cache, 11, "b.zarr", compute)["miou"] == pytest.approx(0.3)  # other store
    assert len(calls) == 3


def test_score_waits_for_the_lock_and_leaves_no_partial_results(tmp_path: Path) -> None:
    import fcntl
    import json
    import threading

    res = tmp_path / "ab.json"
    res.write_text(json.dumps({"runs": {"x-s0": {"row": "x"}}}))
    with open(res.with_name("ab.json.lock"), "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # another scorer is writing
        t = threading.Thread(target=ab.score, args=(6, "none.zarr", 0, tmp_path / "runs", res, None))
        t.start()
        t.join(1.0)
        assert t.is_alive() and "epochs" not in json.loads(res.read_text())  # waits, has not written
    t.join(30)
    assert not t.is_alive()
    out = json.loads(res.read_text())
    assert out["epochs"] == 6 and out["runs"] == {"x-s0": {"row": "x"}}  # kept the other writer's rows
    assert not res.with_name("ab.json.tmp").exists()


def test_step_time_takes_the_second_epoch_and_renders_ratios(tmp_path: Path) -> None:
    import json

    recs = [{"kind": "train", "opt_step": 3}, {"kind": "epoch", "epoch": 1, "opt_step": 5, "seconds": 30.0},
            {"kind": "epoch", "epoch": 2, "opt_step": 9, "seconds": 8.0}]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs[:2]))
    with pytest.raises(SystemExit, match="did not finish 2 epochs"):
        ab._timed_s_per_step(tmp_path)
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    assert ab._timed_s_per_step(tmp_path) == 2.0  # 8 s over steps 5..9, the warm-up epoch left out
    st = {"s_per_step": {"fastocc": 0.5, "3dfcn": 1.0}, "ratio": {"fastocc": 1.0, "3dfcn": 2.0},
          "rounds": [{}, {}], "samples": 40, "threads": 1, "command": "python -m benchmarks.ablations steptime"}
    note = ab._step_time_note(st)
    assert "s/step fastocc 0.50, 3dfcn 1.00 (2.00x)" in note and "median of 2 interleaved rounds" in note
    assert note in ab.render_markdown({"runs": {}, "step_time": st}, 6)
    assert "pending" in ab._step_time_note(None)
    with pytest.raises(SystemExit, match="unknown rows"):
        ab.main(["steptime", "--rows", "fastocc,nope"])


def test_a_killed_call_still_counts_in_the_wall_time(tmp_path: Path) -> None:
    import json
    import os

    run = tmp_path / "hist16-s0"
    ab._open_call(run, 1000.0)  # this call is then SIGKILLed: no end record
    (run / "metrics.jsonl").write_text("{}\n")
    os.utime(run / "metrics.jsonl", (1300.0, 1300.0))  # its trainer's last write
    ab._open_call(run, 2000.0)  # the resuming call closes it
    ab._record_wall(run, 2000.0, 2500.0, 0)
    log = json.loads((run / "ablate_run.json").read_text())
    assert [(c["wall_s"], c["rc"]) for c in log["calls"]] == [(300.0, "killed"), (500.0, 0)]
    assert log["calls"][0]["estimated"] is True and log["wall_s"] == 800.0


def test_two_readings_of_one_paper_row_get_no_paper_order() -> None:
    """bev-only and bev-unfold both stand for the paper's 31.67 row: no "paper < by 0.00" between them."""
    md = ab.render_markdown(_fake_results(), epochs=6)
    line = next(ln for ln in md.splitlines() if ln.startswith("- `bev-only` vs `bev-unfold`"))
    assert "paper" not in line
