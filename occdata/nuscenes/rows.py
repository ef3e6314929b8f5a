"""Typed values out of nuScenes table rows: fields, foreign keys, numbers, poses (one place for all tables).

`field` and `ref` raise `OccDataError` (a broken tree); the value readers raise `RowProblem`, which a
caller either confines to one record (the reader's `SampleRecord.problem`) or turns into an
`OccDataError` naming the table and token.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from occdata.errors import OccDataError
from occdata.geometry import quaternion_problem, rotation_from_quaternion_wxyz

__all__ = ["RowProblem", "field", "floats", "integer", "link", "pose", "ref", "rotation_matrix", "short",
           "timestamp_us"]


class RowProblem(Exception):
    """A value in a row that cannot be used (not numeric, wrong shape, ...); the message names the row."""


def field(row: dict[str, Any], key: str, table: str) -> Any:
    """`row[key]`; a missing field is an `OccDataError` naming the table and the row's token."""
    try:
        return row[key]
    except KeyError:
        raise OccDataError(f"{table}.json: row {row.get('token', '?')!r} has no field {key!r}") from None


def link(row: dict[str, Any], key: str, table: str) -> str:
    """A `prev` / `next` link: a token, or "" at the end of a chain. Missing or not a string is an
    `OccDataError` naming the table, the row and the field."""
    value = field(row, key, table)
    if not isinstance(value, str):
        raise OccDataError(f"{table}.json: row {row.get('token', '?')!r} {key} is not a token ({short(value)})")
    return value


def ref(rows: dict[str, dict[str, Any]], token: Any, table: str, src: str) -> dict[str, Any]:
    """The row of `table` that `src` (e.g. "sample_data 'abc'") refers to; `OccDataError` if dangling."""
    try:
        return rows[token]
    except (KeyError, TypeError):
        raise OccDataError(f"dangling token: {src} refers to {table} {token!r}, not in {table}.json") from None


def short(value: Any) -> str:
    """`repr(value)` cut to 40 characters, for error messages."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def floats(value: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    """`value` as a float64 array of `shape`; NaN stays (callers validate). `RowProblem` otherwise."""
    if isinstance(value, (str, bytes)) or value is None:
        raise RowProblem(f"{where} is not numeric ({short(value)})")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RowProblem(f"{where} is not numeric ({short(value)})") from None
    if arr.shape != shape:
        size = "x".join(map(str, shape)) if len(shape) > 1 else f"{shape[0]} values"
        raise RowProblem(f"{where} has shape {arr.shape}, expected {size}")
    return arr


def integer(value: Any, where: str) -> int:
    """A JSON integer (an integral float is accepted); anything else is a `RowProblem`."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RowProblem(f"{where} is not an integer ({short(value)})")
    if isinstance(value, float) and not value.is_integer():
        raise RowProblem(f"{where} is not an integer ({short(value)})")
    return int(value)


MAX_TIMESTAMP_US = 2**53  # microseconds since 1970: the year 2255; float64 still holds every microsecond


def timestamp_us(value: Any, where: str) -> int:
    """A timestamp in microseconds: a JSON integer, or a finite float rounded to the nearest
    microsecond (ties to even; Lyft Level 5 writes microseconds as floats such as 1557858039302414.8,
    which at that size float64 holds to 0.25 us). Negative, implausibly late (`MAX_TIMESTAMP_US`) or
    non-numeric values are `RowProblem`s."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RowProblem(f"{where} is not a number of microseconds ({short(value)})")
    if isinstance(value, float):
        if not np.isfinite(value):
            raise RowProblem(f"{where} is not finite ({short(value)})")
        value = round(value)
    if value < 0:
        raise RowProblem(f"{where} is negative ({value})")
    if value > MAX_TIMESTAMP_US:
        raise RowProblem(f"{where} is not a plausible time ({short(value)} us is after the year 2255)")
    return int(value)


def rotation_matrix(q_wxyz: Any, where: str) -> np.ndarray:
    """`(3, 3) float64` rotation of a (w, x, y, z) quaternion. Rounding in the files is normalised
    away; a quaternion far from unit length is kept as is, so a later rigidity check reports it.
    A value that is not 4 numbers, not finite or implausibly large raises `RowProblem`."""
    q = floats(q_wxyz, (4,), f"{where} rotation (quaternion w, x, y, z)")
    if (problem := quaternion_problem(q)) is not None:
        raise RowProblem(f"{where} rotation (quaternion w, x, y, z) {problem}")
    n = np.linalg.norm(q)
    return rotation_from_quaternion_wxyz(q, normalise=bool(np.isfinite(n) and abs(n - 1.0) < 1e-3))


def pose(row: dict[str, Any], table: str) -> np.ndarray:
    """`(4, 4) float64` rigid transform of a row's `rotation` (wxyz) and `translation` (ego_pose:
    ego -> global; calibrated_sensor: sensor -> ego)."""
    where = f"{table} {row.get('token', '?')!r}"
    T = np.eye(4)
    T[:3, :3] = rotation_matrix(field(row, "rotation", table), where)
    T[:3, 3] = floats(field(row, "translation", table), (3,), f"{where} translation")
    return T
