"""OpenCL primitives (viewer/cl/primitives.py) against NumPy on random and adversarial inputs."""

from __future__ import annotations

import numpy as np
import pytest

from viewer.cl import context as clctx

U32_MAX = np.uint32(0xFFFFFFFF)


@pytest.fixture(scope="module")
def prims():
    reason = clctx.cl_available()
    if reason is not None:
        pytest.skip(f"no OpenCL device: {reason}")
    from viewer.cl.primitives import primitives

    return primitives()


def _keys(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    if kind == "random":
        return rng.integers(0, 2**32, n, dtype=np.uint32)
    if kind == "few":  # many duplicates: stability matters
        return rng.integers(0, 7, n, dtype=np.uint32)
    if kind == "equal":
        return np.full(n, 12345, np.uint32)
    if kind == "sorted":
        return np.sort(rng.integers(0, 2**32, n, dtype=np.uint32))
    if kind == "reversed":
        return np.sort(rng.integers(0, 2**32, n, dtype=np.uint32))[::-1].copy()
    if kind == "max":  # max uint32 keys mixed with 0 and max - 1
        return rng.choice(np.array([0, U32_MAX - 1, U32_MAX], np.uint32), n)
    if kind == "allmax":
        return np.full(n, U32_MAX, np.uint32)
    if kind == "bits20":  # 3 passes: the odd-pass copy back
        return rng.integers(0, 2**20, n, dtype=np.uint32)
    raise ValueError(kind)


SIZES = [0, 1, 2, 15, 4097, 100_003]
KINDS = ["random", "few", "equal", "sorted", "reversed", "max", "allmax", "bits20"]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("n", SIZES)
def test_sort_pairs_matches_stable_argsort(prims, kind, n):
    from viewer.cl.primitives import sort_pairs_np

    keys = _keys(kind, n, np.random.default_rng(n))
    idx = np.arange(n, dtype=np.uint32)
    ks, vs = sort_pairs_np(keys, idx, prims=prims)
    order = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(ks, keys[order])
    np.testing.assert_array_equal(vs, order)  # values = original index: stability


class _Counting:
    def __init__(self, k):
        self.k, self.calls = k, 0

    def __call__(self, *a, **kw):
        self.calls += 1
        return self.k(*a, **kw)


@pytest.mark.parametrize("max_key,passes", [(0, 0), (1, 1), (255, 1), (256, 2), (2**24 - 1, 3), (2**24, 4),
                                            (2**32 - 1, 4)])
def test_sort_runs_one_pass_per_8_key_bits(prims, monkeypatch, max_key, passes):
    from viewer.cl.primitives import sort_pairs_np

    rng = np.random.default_rng(max_key % 1000)
    keys = rng.integers(0, max_key + 1, 3000, dtype=np.uint64).astype(np.uint32)
    keys[17] = max_key
    counter = _Counting(prims._k["radix_hist"])
    monkeypatch.setitem(prims._k, "radix_hist", counter)
    ks, vs = sort_pairs_np(keys, np.arange(keys.size, dtype=np.uint32), prims=prims)
    assert counter.calls == passes
    order = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(ks, keys[order])
    np.testing.assert_array_equal(vs, order)
    counter.calls = 0  # an explicit key_bits decides the passes
    sort_pairs_np(keys & 0xFFF, keys, key_bits=12, prims=prims)
    assert counter.calls == 2


@pytest.mark.parametrize("kind", ["random", "few"])
def test_sort_2_to_24_pairs(prims, kind):
    """16.7M pairs, checked without a NumPy sort: keys non-decreasing, values a permutation that
    maps back to the keys, and increasing within equal keys (stable)."""
    from viewer.cl.primitives import sort_pairs_np

    n = 1 << 24
    keys = _keys(kind, n, np.random.default_rng(24))
    ks, vs = sort_pairs_np(keys, np.arange(n, dtype=np.uint32), prims=prims)
    assert (ks[1:] >= ks[:-1]).all()
    seen = np.zeros(n, bool)
    seen[vs] = True
    assert seen.all()
    np.testing.assert_array_equal(keys[vs], ks)
    eq = ks[1:] == ks[:-1]
    assert (vs[1:][eq] > vs[:-1][eq]).all()
    np.testing.assert_array_equal(np.bincount(ks % 4096, minlength=4096), np.bincount(keys % 4096, minlength=4096))


@pytest.mark.parametrize("kind,n", [(k, n) for k in ("random", "few", "equal", "allmax", "sorted") for n in SIZES]
                         + [("random", 1 << 24), ("few", 1 << 24)])
def test_exclusive_scan(prims, kind, n):
    from viewer.cl.primitives import exclusive_scan_np

    a = _keys(kind, n, np.random.default_rng(n + 1))
    out, total = exclusive_scan_np(a, prims=prims)
    ref = np.cumsum(a, dtype=np.uint64)  # wraps modulo 2**32 as uint32 addition does
    np.testing.assert_array_equal(out, np.concatenate([np.zeros(1, np.uint64), ref[:-1]]).astype(np.uint32)[:n])
    assert total == (int(ref[-1]) % 2**32 if n else 0)


@pytest.mark.parametrize("density,n", [(d, n) for d in (0.0, 0.03, 0.5, 1.0) for n in SIZES] + [(0.5, 1 << 24)])
def test_compact_by_flags(prims, density, n):
    from viewer.cl.primitives import compact_np

    rng = np.random.default_rng(n)
    vals = rng.integers(0, 2**32, n, dtype=np.uint32)
    flags = (rng.random(n) < density).astype(np.uint32) * rng.integers(1, 2**32, n, dtype=np.uint32)
    kept, idx = compact_np(vals, flags, prims=prims)
    want = flags != 0
    np.testing.assert_array_equal(kept, vals[want])
    np.testing.assert_array_equal(idx, np.flatnonzero(want))


def test_compact_rows_and_predicate(prims):
    from viewer.cl.primitives import compact_np

    rng = np.random.default_rng(5)
    n = 50_001
    rays = rng.normal(size=(n, 4)).astype(np.float32)  # float4 rows, moved as uint4
    flags = (rays[:, 3] > 0).astype(np.uint32)
    kept, idx = compact_np(rays, flags, prims=prims)
    np.testing.assert_array_equal(kept, rays[flags != 0])
    np.testing.assert_array_equal(idx, np.flatnonzero(flags))
    keys = rng.choice(np.array([3, 7, U32_MAX], np.uint32), n)
    kept, idx = compact_np(keys, predicate="x != 0xffffffffu", prims=prims)
    np.testing.assert_array_equal(kept, keys[keys != U32_MAX])
    np.testing.assert_array_equal(idx, np.flatnonzero(keys != U32_MAX))
    pairs = rng.integers(0, 10, (n, 2), dtype=np.uint32)
    kept, idx = compact_np(pairs, predicate="x.x < x.y", prims=prims)
    np.testing.assert_array_equal(kept, pairs[pairs[:, 0] < pairs[:, 1]])
    with pytest.raises(ValueError):
        prims.compact(10)


@pytest.mark.parametrize("what", ["items", "index"])
def test_compact_one_output(prims, what):
    """Items only or indices only: the other output is not touched."""
    ctx = prims.ctx
    cl = ctx.cl
    rng = np.random.default_rng(9)
    n = 70_001
    vals = rng.integers(0, 2**32, n, dtype=np.uint32)
    flags = (rng.random(n) < 0.3).astype(np.uint32)
    mf = cl.mem_flags
    vb = cl.Buffer(ctx.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=vals)
    fb = cl.Buffer(ctx.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=flags)
    sentinel = np.full(n, 7, np.uint32)
    ob = cl.Buffer(ctx.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=sentinel)
    kw = {"dst": ob} if what == "items" else {"dst_index": ob}
    m = prims.compact(n, flags=fb, src=vb, **kw)
    out = np.empty(n, np.uint32)
    cl.enqueue_copy(ctx.queue, out, ob)
    want = vals[flags != 0] if what == "items" else np.flatnonzero(flags)
    assert m == want.size
    np.testing.assert_array_equal(out[:m], want)
    assert (out[m:] == 7).all()  # nothing written past the kept count


def _chunks_ref(k: np.ndarray, r: int | None):
    n = k.size
    if n == 0:
        return (np.zeros(0, np.uint32),) * 3
    starts = np.flatnonzero(np.concatenate([[True], k[1:] != k[:-1]]))
    ends = np.concatenate([starts[1:], [n]])
    lens = ends - starts
    if r is None:
        return k[starts], starts, lens
    nch = -(-lens // r)
    seg = np.repeat(np.arange(starts.size), nch)
    within = np.arange(nch.sum()) - np.repeat(np.cumsum(nch) - nch, nch)
    cstart = starts[seg] + within * r
    return k[cstart], cstart, np.minimum(r, ends[seg] - cstart)


@pytest.mark.parametrize("kind,n,r", [(k, n, r) for k in ("random", "few", "equal", "sorted", "max", "runs")
                                      for n in SIZES for r in (1, 3, 64, None)]
                         + [(k, 1 << 22, r) for k in ("runs", "few") for r in (3, 64, None)])
def test_segments_and_chunks(prims, kind, n, r):
    from viewer.cl.primitives import segments_np

    rng = np.random.default_rng(n + 7)
    if kind == "runs":  # runs of random lengths 1..500 crossing block boundaries
        lengths = rng.integers(1, 500, n // 125 + 2)
        k = np.repeat(np.arange(lengths.size, dtype=np.uint32) * 3, lengths)[:n]
    else:
        k = np.sort(_keys(kind, n, rng))
    got = segments_np(k, r, prims=prims)
    for g, w, name in zip(got, _chunks_ref(k, r), ("key", "start", "count"), strict=True):
        np.testing.assert_array_equal(g, w, err_msg=name)


@pytest.mark.parametrize("dtype,n", [(d, n) for d in (np.uint32, np.int32, np.float32) for n in (1, 2, 4097, 100_003)]
                         + [(np.uint32, 1 << 24)])
def test_min_max_reduce(prims, dtype, n):
    from viewer.cl.primitives import reduce_np

    rng = np.random.default_rng(n)
    if dtype == np.float32:
        a = (rng.normal(size=n) * 1e6).astype(np.float32)
        a[rng.integers(0, n)] = -np.inf
    elif dtype == np.int32:
        a = rng.integers(-(2**31), 2**31, n, dtype=np.int64).astype(np.int32)
    else:
        a = _keys("random", n, rng)
        a[-1] = U32_MAX  # the identity of max is 0 and of min is U32_MAX: both must still win
    assert reduce_np(a, "min", prims=prims) == a.min()
    assert reduce_np(a, "max", prims=prims) == a.max()
    with pytest.raises(ValueError):
        prims.reduce(None, 0)


def test_bad_arguments(prims):
    with pytest.raises(ValueError, match="key_bits"):
        prims.sort_pairs(None, None, 10, key_bits=33)
    with pytest.raises(ValueError, match="r must be"):
        prims.segments(None, 10, r=0)
