"""The embedding cache: entries written by a thread of their own, a read of one still being
written waiting for it; its bound: past `max_bytes` the least recently used entries go, a read
renews an entry's use, the entry just written always stays, and a bad bound is refused."""

import os

import numpy as np
import pytest

from sagonline.segment.embedding import CACHE_FORMAT
from sagonline.segment.embedding_cache import EmbeddingCache

ARRAY = np.zeros((64, 64), np.float32)  # 16 KiB an entry


def record(key: str) -> dict:
    return {"format": CACHE_FORMAT, "frame": key, "encoder": "e" * 64}


def expected(key: str) -> dict:
    return {**record(key), "arrays": {"features": [[64, 64], "float32"]}}


def put(cache: EmbeddingCache, key: str, age_s: float) -> None:
    """Save an entry and date its last use `age_s` seconds ago."""
    cache.save(key, record(key), {"features": ARRAY + len(key)})
    cache.flush()
    when = os.path.getmtime(cache.path(key)) - age_s
    os.utime(cache.path(key), (when, when))


def test_past_its_bound_the_least_recently_used_entries_go(tmp_path):
    unbounded = EmbeddingCache(tmp_path)
    for i in range(5):
        put(unbounded, f"k{i}", age_s=100 - i)  # k0 the oldest
    entry = os.path.getsize(unbounded.path("k0"))
    assert len(list(tmp_path.glob("*.store"))) == 5  # no bound: all stay

    # room for 5.5 entries; k1 is read, so it counts as used now
    cache = EmbeddingCache(tmp_path, max_bytes=int(5.5 * entry))
    assert cache.load("k1", expected("k1")) is not None
    put(cache, "k5", age_s=0)  # 6 entries > the bound: trimmed to 0.8 x 5.5 = 4.4 entries
    left = sorted(p.stem for p in tmp_path.glob("*.store"))
    assert left == ["k1", "k4", "k5"] or left == ["k1", "k3", "k4", "k5"]
    assert sum(p.stat().st_size for p in tmp_path.glob("*.store")) <= 0.8 * 5.5 * entry
    assert "k0" not in left and "k2" not in left  # the oldest unread went first


def test_the_entry_just_written_stays_even_when_it_alone_is_past_the_bound(tmp_path):
    cache = EmbeddingCache(tmp_path, max_bytes=100)  # smaller than one entry
    put(cache, "old", age_s=10)
    put(cache, "new", age_s=0)
    assert [p.stem for p in tmp_path.glob("*.store")] == ["new"]
    assert cache.load("new", expected("new")) is not None


def test_an_entry_trimmed_by_another_process_is_a_miss_not_a_warning(tmp_path, recwarn):
    cache = EmbeddingCache(tmp_path, max_bytes=10**9)
    put(cache, "k", age_s=0)
    cache.path("k").unlink()  # as another process's trim would
    assert cache.load("k", expected("k")) is None
    assert not [w for w in recwarn if "embedding cache" in str(w.message)]


@pytest.mark.parametrize("bad", [0, -1, "x"])
def test_a_bound_that_is_not_positive_is_refused_naming_the_option(bad):
    from sagonline.core.plugins import SEGMENTERS

    plugin = SEGMENTERS["minisam"]
    with pytest.raises(ValueError, match="embedding_cache_gb"):
        plugin.build(plugin.settings({"embedding_cache_gb": bad}, where="segmenter minisam"))


def test_the_bound_reaches_the_model_cache_in_bytes():
    from sagonline.segment.sam_prompting import gigabytes

    assert gigabytes(4.0) == 4_000_000_000 and gigabytes(None) is None


def test_an_entry_is_written_in_the_background_and_a_read_waits_for_it(tmp_path, monkeypatch):
    """`save` hands the entry to the writer thread and returns; a read of it, from this cache
    or another on the same folder, waits until it is on disk, whole."""
    import threading

    from sagonline.core import store

    release, writers = threading.Event(), []
    save = store.save

    def slow_save(path, value):
        writers.append(threading.current_thread().name)
        release.wait(10)
        return save(path, value)

    monkeypatch.setattr(store, "save", slow_save)
    cache = EmbeddingCache(tmp_path / "emb")
    cache.save("k", record("k"), {"features": ARRAY + 1})  # returns with the write held back
    assert not cache.path("k").exists()
    threading.Timer(0.2, release.set).start()
    got = EmbeddingCache(tmp_path / "emb").load("k", expected("k"))
    assert got is not None and np.array_equal(got["features"], ARRAY + 1)
    assert writers and all(name.startswith("embedding-cache") for name in writers)


def test_a_forked_child_neither_waits_for_its_parents_writes_nor_loses_its_own(
    tmp_path, monkeypatch
):
    """A write still held back in the parent at the fork is not the child's to wait for (its
    thread is not in the child): the child's read is a miss at once, and its own write lands."""
    import signal
    import threading
    import time

    from sagonline.core import store

    release = threading.Event()
    save = store.save
    monkeypatch.setattr(store, "save", lambda path, value: release.wait(10) and save(path, value))
    cache = EmbeddingCache(tmp_path)
    cache.save("held", record("held"), {"features": ARRAY})
    pid = os.fork()
    if pid == 0:  # the child: a miss, then its own entry written by its own thread
        monkeypatch.setattr(store, "save", save)
        ok = cache.load("held", expected("held")) is None
        cache.save("child", record("child"), {"features": ARRAY + 2})
        cache.flush()
        os._exit(0 if ok and cache.path("child").is_file() else 1)
    deadline = time.monotonic() + 20
    while (done := os.waitpid(pid, os.WNOHANG))[0] == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    if done[0] == 0:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    release.set()
    cache.flush()
    assert done[0] == pid and os.waitstatus_to_exitcode(done[1]) == 0
    assert cache.load("child", expected("child")) is not None
    assert cache.load("held", expected("held")) is not None
