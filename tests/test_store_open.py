"""Issue 48: a store opens, and the loader reaches its first sample, in a number of requests that does not
grow with the sample count; the small arrays come from their packed copies, once per process tree.

Requests are counted at zarr's store interface (every get, partial get, existence check and listing
of `LocalStore`: on an object store each is one request) and, for S3, at the HTTP level through the
benchmark's proxy in front of a local moto server. The stores replay one built block
(`benchmarks/tiled_store.py`) at two sizes.
"""

from __future__ import annotations

import pickle
import shutil
import threading
import warnings
from collections import Counter
from multiprocessing.reduction import ForkingPickler
from pathlib import Path

import numpy as np
import pytest
import torch.multiprocessing  # noqa: F401 - registers the shared-memory reductions of tensors
import zarr

from benchmarks.tiled_store import make_tiled_store
from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, StoreDataset
from fastocc.data.sample import StoreSamples
from occdata.store.create import consolidate
from occdata.store.pack import PACK_ATTR, drop_pack, pack_names, write_pack
from occdata.store.reader import open_store

SMALL = SampleConfig(image=ImageAugConfig(height=96, width=160, train=False), bev=BevAugConfig(train=False))
_CALLS = ("get", "get_partial_values", "exists", "list", "list_prefix", "list_dir", "getsize")


@pytest.fixture(scope="module")
def tiled(synth_store: Path, tmp_path_factory) -> dict[int, Path]:
    """The 6-sample synthetic store (one block of 6) replayed to 24 and 240 samples (4 and 40 blocks)."""
    tmp = tmp_path_factory.mktemp("tiled")
    return {n: make_tiled_store(synth_store, tmp / f"t{n}.zarr", n) for n in (24, 240)}


@pytest.fixture
def count_requests(monkeypatch) -> Counter:
    """Counts calls of LocalStore's reading methods, by method name."""
    counts: Counter = Counter()
    cls = zarr.storage.LocalStore
    for name in _CALLS:
        original = getattr(cls, name)

        def wrapped(self, *args, _name=name, _original=original, **kwargs):
            counts[_name] += 1
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(cls, name, wrapped)
    return counts


def _first_sample(store: Path) -> int:
    ds = StoreDataset(LoaderConfig(store=store, batch_size=1, sample=SMALL))
    return int(next(iter(ds)).sample_index[0])


def _requests_to_first_sample(store: Path, counts: Counter) -> int:
    counts.clear()
    _first_sample(store)
    # get_partial_values takes several ranges at once: on an object store each range is a request
    return sum(counts.values())


def test_requests_to_open_and_read_the_first_sample_do_not_grow(tiled, count_requests) -> None:
    """Was: every small array read chunk by chunk, each chunk's key found through a metadata read, and
    each array's chunks listed: ~35 requests per block of samples (1,400 at 40 blocks)."""
    small = _requests_to_first_sample(tiled[24], count_requests)
    large = _requests_to_first_sample(tiled[240], count_requests)
    assert large == small, (small, large)
    assert large <= 80, count_requests


def test_without_packed_copies_a_store_still_opens_from_its_chunks(tiled, tmp_path: Path, count_requests) -> None:
    """A store from before the packed copies (or one a build is still writing): the same samples, read
    from the block chunks (more requests, growing with the blocks)."""
    old = tmp_path / "old.zarr"
    shutil.copytree(tiled[240], old)
    root = zarr.open_group(str(old), mode="r+")
    drop_pack(root)
    shutil.rmtree(old / "pack")
    consolidate(str(old))
    packed = StoreDataset(LoaderConfig(store=tiled[240], batch_size=1, sample=SMALL))
    chunked = StoreDataset(LoaderConfig(store=old, batch_size=1, sample=SMALL))
    assert np.array_equal(packed.indices, chunked.indices)
    for name in pack_names(root.attrs):
        assert np.array_equal(packed.samples().reader.small(name), chunked.samples().reader.small(name)), name
    assert _requests_to_first_sample(old, count_requests) > 40 * 10  # >= one chunk per block of each array


def test_a_store_without_consolidated_metadata_opens(tiled, tmp_path: Path) -> None:
    """zarr drops the consolidated copy when a root attribute is written through a plain handle (older
    writers did so): the reader then opens array by array."""
    old = tmp_path / "noconsolidated.zarr"
    shutil.copytree(tiled[24], old)
    zarr.open_group(str(old), mode="r+", use_consolidated=False).attrs["note"] = "edited"
    reader = open_store(old, packed=True)
    assert not reader.consolidated and reader.n_samples == 24
    assert _first_sample(old) in range(24)


def test_the_packed_copies_equal_the_chunks_and_their_digest_is_their_content(tiled, tmp_path: Path) -> None:
    store = tmp_path / "s.zarr"
    shutil.copytree(tiled[24], store)
    root = zarr.open_group(str(store), mode="r+")
    generation = root.attrs[PACK_ATTR]["generation"]
    for name in pack_names(root.attrs):
        assert np.array_equal(root[f"pack/{name}"][...], root[name][:]), name
    write_pack(root)  # the same content: the same generation (a resumed build's store is identical)
    assert root.attrs[PACK_ATTR]["generation"] == generation
    root["calib/K"][3] = 0.0
    write_pack(root)
    assert root.attrs[PACK_ATTR]["generation"] != generation


def test_a_stale_or_damaged_pack_is_not_used(tiled, tmp_path: Path) -> None:
    store = tmp_path / "s.zarr"
    shutil.copytree(tiled[24], store)
    root = zarr.open_group(str(store), mode="r+")
    committed = np.asarray(root["calib/K"][:])
    # A writer that drops the pack before changing a small array: readers read the chunks.
    drop_pack(root)
    root["calib/K"][0] = 7.0
    consolidate(str(store))
    assert (open_store(store, packed=True).small("calib/K")[0] == 7.0).all()
    # A packed copy changed after its commit (damage that still decodes): its crc32 differs, one warning
    # line, the chunks are read. One that no longer decodes is read from the chunks as well.
    root["calib/K"][:] = committed
    write_pack(root)
    consolidate(str(store))
    root["pack/calib/K"][0] = 5.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert np.array_equal(open_store(store, packed=True).small("calib/K"), committed)
    assert [str(w.message) for w in caught if "packed copy of calib/K is damaged" in str(w.message)], caught
    (chunk,) = [p for p in (store / "pack/calib/K/c").rglob("*") if p.is_file()]
    chunk.write_bytes(b"not zstd")
    assert np.array_equal(open_store(store, packed=True).small("calib/K"), committed)


def test_pickled_samples_travel_in_shared_memory_and_reread_nothing(tiled, count_requests) -> None:
    """What a forkserver/spawn loader worker gets: the small arrays unpickled without a store read (the
    worker opens the root metadata only), equal to the parent's, read-only."""
    parent = StoreSamples(open_store(tiled[240], packed=True))
    data = ForkingPickler.dumps(parent)
    assert len(data) < 10_000  # descriptors, not the arrays
    count_requests.clear()
    child = pickle.loads(data)
    child.reader.small("sample/token")
    child.reader.integrity.checksums()
    assert sum(count_requests.values()) <= 2, count_requests  # the root zarr.json (+ a probe)
    for name in ("state", "K", "T_global_from_keyego", "prev_index", "img_off", "uvd_off"):
        assert np.array_equal(getattr(child, name), getattr(parent, name)), name
        assert not getattr(child, name).flags.writeable
    assert ForkingPickler.dumps(parent) is not None and parent._shared is not None  # copied once, kept


@pytest.mark.slow
def test_s3_requests_to_the_first_sample_do_not_grow(tiled, monkeypatch) -> None:
    """The same over HTTP: a local S3 server behind the benchmark's counting proxy (no added latency).
    Was: ~2 requests (a HEAD, then the GET) per small chunk, plus listings, per block."""
    pytest.importorskip("s3fs")
    moto_server = pytest.importorskip("moto.server")
    from benchmarks.bench_open import LatencyProxy, _free_port, upload

    port = _free_port()
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    proxy = LatencyProxy(port, 0.0)
    thread = threading.Thread(target=proxy.serve_forever, daemon=True)
    thread.start()
    creds = {"AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1"}
    try:
        counts = {}
        for n, local in tiled.items():
            upload(local, f"s3://open-test/t{n}.zarr", {**creds, "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}"})
        for k, v in {**creds, "AWS_ENDPOINT_URL": f"http://127.0.0.1:{proxy.server_address[1]}"}.items():
            monkeypatch.setenv(k, v)
        import fsspec

        fsspec.filesystem("s3").clear_instance_cache()
        for n in tiled:
            before = proxy.requests
            _first_sample(f"s3://open-test/t{n}.zarr")
            counts[n] = proxy.requests - before
    finally:
        proxy.shutdown()
        server.stop()
    assert counts[240] == counts[24] and counts[240] <= 80, counts


def test_the_first_batch_reads_one_block(tiled, monkeypatch) -> None:
    """Was: the shuffle buffer (64) filled with whole blocks before the first draw: 11 block reads here
    (blocks of 6). The order is planned on indices; a block is read when its first sample is drawn."""
    reads = []
    original = StoreSamples.read_run

    def counted(self, lo, hi, wanted=None):
        reads.append((lo, hi))
        return original(self, lo, hi, wanted)

    monkeypatch.setattr(StoreSamples, "read_run", counted)
    ds = StoreDataset(LoaderConfig(store=tiled[240], batch_size=2, sample=SMALL))
    it = iter(ds)
    first = next(it)
    assert len(reads) <= 2  # the two samples' blocks
    assert {int(i) // 6 for i in first.sample_index} == {lo // 6 for lo, _ in reads}
    monkeypatch.setattr(StoreSamples, "read_run", original)
    whole = [int(i) for b in [first, *it] for i in b.sample_index]
    assert sorted(whole) == list(range(240))  # every sample once: the lazy reads lose none


def test_a_blocks_arrays_are_read_in_one_round_trip(tiled, monkeypatch) -> None:
    """The loader reads a block's images, depth and four label arrays concurrently: over an object
    store one round trip, not six in a row (each chunk read here waits 20 ms, as a request would)."""
    import asyncio

    data = {"images/jpeg", "depth/uvd", "labels/semantics", "labels/mask_camera", "labels/mask_lidar", "labels/bev"}
    in_flight: Counter = Counter()
    most = [0]
    original = zarr.storage.LocalStore.get

    async def slow_get(self, key, *args, **kwargs):
        name = key.rsplit("/c/", 1)[0] if "/c/" in key else ""
        if name in data:
            in_flight[name] += 1
            most[0] = max(most[0], sum(1 for v in in_flight.values() if v))
        try:
            await asyncio.sleep(0.02)
            return await original(self, key, *args, **kwargs)
        finally:
            if name in data:
                in_flight[name] -= 1

    monkeypatch.setattr(zarr.storage.LocalStore, "get", slow_get)
    _first_sample(tiled[24])
    assert most[0] == len(data), most[0]


def test_packed_copies_are_written_a_chunk_of_rows_at_a_time(tiled, tmp_path: Path, monkeypatch) -> None:
    """Past `PACK_ROWS` samples a packed copy has several chunks (the commit holds one chunk of one array,
    whatever the size): readers take it (its crc32 is the whole array's), and it equals the chunks."""
    import occdata.store.pack as pack

    store = tmp_path / "s.zarr"
    shutil.copytree(tiled[24], store)
    monkeypatch.setattr(pack, "PACK_ROWS", 5)
    root = zarr.open_group(str(store), mode="r+")
    write_pack(root)
    consolidate(str(store))
    root = zarr.open_group(str(store), mode="r")  # the metadata just consolidated
    reader = open_store(store, packed=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a crc mismatch would warn and fall back to the chunks
        for name in pack_names(root.attrs):
            assert root[f"pack/{name}"].chunks[0] == 5, name
            assert np.array_equal(reader.small(name), root[name][:]), name
            assert reader._packed(name) is not None, name
