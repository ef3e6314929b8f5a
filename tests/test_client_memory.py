"""Issue 48: what the build and labels clients hold per sample. Table rows share their keys and
repeated tokens; records share their sensor's calibration (read-only); tasks are made only when
sent. The peak RSS against the sample count is measured by benchmarks/bench_client_memory.py."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from replicated_tree import make_replicated_tree

from occdata.nuscenes import load_nuscenes
from occdata.nuscenes.tables import load_table
from occdata.runtime.cluster import LazyTasks, run_tasks


def test_kept_rows_share_keys_and_repeated_tokens(tmp_path: Path) -> None:
    """Two rows decoded apart: equal keys and the sample token they both name are one object each
    (the decoder made separate copies per row); a long file name is left alone."""
    rows = [{"token": f"sd{k}", "sample_token": "s" + "0" * 31, "filename": "samples/" + "x" * 80 + str(k)}
            for k in range(2)]
    path = tmp_path / "sample_data.json"
    path.write_text(json.dumps(rows))
    a, b = load_table(path).values()
    assert a == rows[0] and b == rows[1]
    key_a = next(k for k in a if k == "sample_token")
    key_b = next(k for k in b if k == "sample_token")
    assert key_a is key_b
    assert a["sample_token"] is b["sample_token"]


def test_records_share_their_sensors_calibration_read_only(real_nuscenes_root, real_occ3d_label,
                                                            tmp_path: Path) -> None:
    tree = make_replicated_tree(real_nuscenes_root, real_occ3d_label, tmp_path / "ns", 1, 3, labels=False)
    ds = load_nuscenes(tree)
    first, second = ds.samples[0], ds.samples[1]
    for c0, c1 in zip(first.cameras, second.cameras, strict=True):
        assert c0.K is c1.K and c0.T_ego_from_cam is c1.T_ego_from_cam
        assert c0.T_global_from_ego is not c1.T_global_from_ego  # each row's own pose
        with pytest.raises(ValueError):
            c0.K[0, 0] = 1.0
    assert first.lidar.T_ego_from_lidar is second.lidar.T_ego_from_lidar
    assert np.isfinite(first.cameras[0].K).all() and first.cameras[0].K[2, 2] == 1.0


@dataclass(frozen=True)
class _Unit:
    k: int
    made: list[int]
    ran: list[tuple[int, int]]
    units: int = 1

    def run(self, should_stop) -> int:
        self.ran.append((self.k, max(self.made)))  # the newest task made when this one runs
        return self.k


def test_lazy_tasks_are_made_one_at_a_time_in_this_process() -> None:
    """In this process a task is made just before it runs: when task k runs, none after it exists."""
    made: list[int] = []
    ran: list[tuple[int, int]] = []

    def make(k: int) -> _Unit:
        made.append(k)
        return _Unit(k, made, ran)

    results: list[int] = []
    run_tasks(None, LazyTasks(range(5), make), desc="t", progress=False, total=5,
              on_result=lambda t, r: results.append(r))
    assert results == [0, 1, 2, 3, 4] and made == [0, 1, 2, 3, 4]
    assert ran == [(k, k) for k in range(5)]
