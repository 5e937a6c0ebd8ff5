"""The on-disk cache of prepared subjects (jaxface.fit.subject_cache) and the host-side
input check of the fit's forward model, whose compiled programs can be cached by JAX."""

import dataclasses
import os
import pickle
import warnings
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxface.errors import RigError
from jaxface.fit.subject import SubjectOptions, prepare_subject
from jaxface.fit.subject_cache import (
    CachedParts,
    SubjectCache,
    UncacheableError,
    default_subject_cache_dir,
    resolve_subject_cache,
    subject_key,
)


def _key_inputs():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(30, 3)) * 50
    tr = rng.integers(0, 30, size=(40, 3))
    lm = {"Nose tip": v[0].copy(), "Chin middle": v[1].copy()}
    return v, tr, lm


def test_key_follows_the_content_not_the_object():
    v, tr, lm = _key_inputs()
    opt = SubjectOptions(levels=2, pitch_knots=6)
    k = subject_key(v, tr, lm, None, None, opt)
    # the same content in other objects and dtypes: the same key
    assert (
        subject_key(
            v.copy(),
            tr.astype(np.int32),
            dict(lm),
            None,
            None,
            SubjectOptions(levels=2, pitch_knots=6),
        )
        == k
    )
    # any change of what the build reads: another key
    moved = dict(lm)
    moved["Nose tip"] = lm["Nose tip"] + [0.0, 0.0, 1e-3]
    v2 = v.copy()
    v2[5, 1] += 0.01
    others = [
        subject_key(v2, tr, lm, None, None, opt),
        subject_key(v, tr[::-1], lm, None, None, opt),
        subject_key(v, tr, moved, None, None, opt),
        subject_key(v, tr, {"Nose tip": lm["Nose tip"]}, None, None, opt),
        subject_key(v, tr, lm, None, None, SubjectOptions(levels=3, pitch_knots=6)),
        subject_key(v, tr, lm, None, None, SubjectOptions(levels=2, pitch_knots=6, backend="ltw")),
        subject_key(
            v,
            tr,
            lm,
            None,
            None,
            SubjectOptions(levels=2, pitch_knots=6, rig_kwargs={"skin_iterations": 9}),
        ),
        subject_key(v, tr, lm, SimpleNamespace(vertices=v, triangles=tr), None, opt),
    ]
    assert len({k, *others}) == len(others) + 1
    # a template mesh is keyed by its content
    t1 = subject_key(v, tr, lm, SimpleNamespace(vertices=v * 2, triangles=tr), None, opt)
    t2 = subject_key(v, tr, lm, SimpleNamespace(vertices=v * 2, faces=tr), None, opt)
    assert t1 == t2 != others[-1]


def test_key_refuses_what_it_cannot_describe():
    v, tr, lm = _key_inputs()
    with pytest.raises(UncacheableError, match="template"):
        subject_key(v, tr, lm, object(), None, SubjectOptions())
    with pytest.raises(UncacheableError, match="rig_kwargs"):
        subject_key(v, tr, lm, None, None, SubjectOptions(rig_kwargs={"f": lambda x: x}))


def _parts(n: int) -> CachedParts:
    return CachedParts(
        registration={"vertices": np.arange(n, dtype=float)},
        rig=None,
        response=np.ones((n, 3)),
        fit_ids=np.arange(n),
        face_triangles=np.ones(n, bool),
        landmark_names=("a",),
        landmark_tri=np.zeros(1, np.int64),
        landmark_bary=np.full((1, 3), 1 / 3),
        timings={"rig_s": 1.0},
    )


def test_store_load_and_damaged_entries(tmp_path):
    cache = SubjectCache(tmp_path / "c")
    assert cache.load("0" * 64) is None  # a miss, nothing created
    p = cache.store("a" * 64, _parts(10))
    assert p is not None and p.is_file()
    got = cache.load("a" * 64)
    assert isinstance(got, CachedParts)
    np.testing.assert_array_equal(got.response, np.ones((10, 3)))
    assert not list((tmp_path / "c").glob(".*tmp*"))  # no temporary file left
    # a truncated entry: a warning, the file removed, a miss
    p.write_bytes(p.read_bytes()[:50])
    with pytest.warns(UserWarning, match="unreadable"):
        assert cache.load("a" * 64) is None
    assert not p.exists()
    # an entry whose stored key is another's (a prefix collision) is not used
    cache.store("b" * 64, _parts(3))
    other = cache.path("b" * 32 + "c" * 32)
    assert other == cache.path("b" * 64)
    with pytest.warns(UserWarning, match="another key"):
        assert cache.load("b" * 32 + "c" * 32) is None


def test_side_entries_live_and_go_with_their_entry(tmp_path):
    cache = SubjectCache(tmp_path)
    k = "d" * 64
    assert cache.store_json(k, "noise-floor-x", {"AU1": 0.1}) is None  # no entry: not kept
    cache.store(k, _parts(5))
    assert cache.store_json(k, "noise-floor-x", {"AU1": 0.1}) is not None
    assert cache.load_json(k, "noise-floor-x") == {"AU1": 0.1}
    assert cache.load_json(k, "noise-floor-y") is None
    cache.side_path(k, "noise-floor-x").write_text("{not json")
    with pytest.warns(UserWarning, match="unreadable"):
        assert cache.load_json(k, "noise-floor-x") is None
    assert not cache.side_path(k, "noise-floor-x").exists()
    cache.store_json(k, "noise-floor-x", {"AU1": 0.1})
    assert cache.clear() == 1 and not list(tmp_path.iterdir())


def test_trim_removes_the_entries_used_longest_ago(tmp_path):
    size = len(pickle.dumps(("k" * 64, _parts(2000)), protocol=pickle.HIGHEST_PROTOCOL))
    cache = SubjectCache(tmp_path, max_bytes=int(2.5 * size))
    keys = [c * 64 for c in "abc"]
    cache.store(keys[0], _parts(2000))
    cache.store(keys[1], _parts(2000))
    os.utime(cache.path(keys[0]), (1e9, 1e9))
    os.utime(cache.path(keys[1]), (1.1e9, 1.1e9))
    assert cache.load(keys[0]) is not None  # used now: the newest
    cache.store(keys[2], _parts(2000))  # over the limit: the oldest used (b) goes
    assert sorted(p.name for p in cache.entries()) == sorted(
        cache.path(k).name for k in (keys[0], keys[2])
    )
    assert cache.clear() == 2 and cache.entries() == []
    # an entry larger than the whole limit is not written
    assert SubjectCache(tmp_path, max_bytes=100).store(keys[0], _parts(2000)) is None


def test_resolve(tmp_path, monkeypatch):
    monkeypatch.delenv("JAXFACE_SUBJECT_CACHE", raising=False)
    assert resolve_subject_cache(None) is None
    for off in ("off", "OFF", "none", ""):
        assert resolve_subject_cache(off) is None
    assert resolve_subject_cache(tmp_path).folder == tmp_path
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert resolve_subject_cache("default").folder == tmp_path / "xdg" / "jaxface" / "subjects"
    assert default_subject_cache_dir() == tmp_path / "xdg" / "jaxface" / "subjects"
    monkeypatch.setenv("JAXFACE_SUBJECT_CACHE", str(tmp_path / "env"))
    assert resolve_subject_cache(None).folder == tmp_path / "env"
    c = SubjectCache(tmp_path / "own")
    assert resolve_subject_cache(c) is c


def test_a_cached_subject_is_the_fresh_build(shared, tmp_path):
    """A build, then the same build from the cache: the same registration, rig, reduced model
    and syntheses; the second skips the registration, the rig and the sampling."""
    from jaxface.io import load_scan

    root = shared("data", "bosphorus_style")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        neutral = load_scan(root / "bs900_N_N_0.bnt")
    opt = SubjectOptions(levels=1, pitch_knots=3)
    cache = SubjectCache(tmp_path)
    said_a: list[str] = []
    a = prepare_subject(neutral, options=opt, cache=cache, progress=said_a.append)
    assert len(cache.entries()) == 1
    said_b: list[str] = []
    b = prepare_subject(neutral, options=opt, cache=cache, progress=said_b.append)
    assert {"register_s", "rig_s", "response_s"} <= set(a.timings)
    assert "cache_load_s" in b.timings and not {"register_s", "rig_s", "response_s"} & set(
        b.timings
    )
    assert any("loaded" in s for s in said_b) and not any("sampling" in s for s in said_b)
    np.testing.assert_array_equal(a.registration.vertices, b.registration.vertices)
    np.testing.assert_array_equal(a.fit_ids, b.fit_ids)
    for x, y in zip(jax.tree_util.tree_leaves(a.response), jax.tree_util.tree_leaves(b.response)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    rng = np.random.default_rng(1)
    act = rng.uniform(0, 0.6, a.forward.n_controls)
    jaw = np.array([6.0, 1.0, 0.5])
    np.testing.assert_array_equal(a.forward(act, jaw), b.forward(act, jaw))
    assert len(cache.entries()) == 1
    # the first fit keeps the AU readout's noise floor beside the entry; a fit of the loaded
    # subject reads it instead of fitting the neutral to itself again (fit_expressions runs
    # set_noise_floor with the self-fit; here a counted stand-in for the self-fit)
    from jaxface.fit.options import FitOptions
    from jaxface.fit.pipeline import set_noise_floor

    fast, other = FitOptions(max_steps=10), FitOptions(max_steps=11)
    calls: list[int] = []

    def self_fit():
        calls.append(1)
        return {"AU1": 0.01 * len(calls), "AU12": 0.02}

    set_noise_floor(a, fast, self_fit)
    assert a.au_noise_floor == {"AU1": 0.01, "AU12": 0.02} and len(calls) == 1
    assert a.cache_key == b.cache_key
    said_c: list[str] = []
    set_noise_floor(b, fast, self_fit, said_c.append)
    assert b.au_noise_floor == a.au_noise_floor and len(calls) == 1
    assert any("from the subject cache" in s for s in said_c)
    set_noise_floor(b, other, self_fit)  # other options: another floor
    assert b.au_noise_floor == {"AU1": 0.02, "AU12": 0.02} and len(calls) == 2
    assert len(list(tmp_path.glob("noise-floor-*.json"))) == 2
    # without a cache: computed every time
    c = dataclasses.replace(b, cache=None, cache_key=None, au_noise_floor=None)
    set_noise_floor(c, fast, self_fit)
    assert len(calls) == 3
    assert cache.clear() == 1 and not list(tmp_path.iterdir())


def test_forward_model_checks_on_the_host_and_compiles_without_callbacks(default_rig):
    """The fit's compiled synthesis carries no host callback (JAX would not cache it on
    disk), while the public synthesize keeps its traced check; NaN is refused on the host."""
    from jaxface.fit.forward import ForwardModel, synthesis_function

    M = default_rig.n_controls
    a, j = jnp.zeros(M), jnp.zeros(3)
    fit_text = jax.jit(synthesis_function(default_rig)).lower(a, j).as_text()
    from jaxface.anatomy.jaw import JawPose

    public_text = (
        jax.jit(lambda a, j: default_rig.synthesize(a, JawPose.from_array(j))).lower(a, j).as_text()
    )
    assert "callback" in public_text  # the positive control: eqx.error_if's host callback
    assert "callback" not in fit_text
    fm = ForwardModel(default_rig)
    bad = np.zeros(M)
    bad[3] = np.nan
    with pytest.raises(RigError, match="NaN"):
        fm(bad, np.zeros(3))
    with pytest.raises(RigError, match="NaN"):
        fm.with_vjp(np.zeros(M), np.array([np.inf, 0.0, 0.0]))
    with pytest.raises(RigError, match="NaN"):
        fm.many(np.stack([np.zeros(M), bad]), np.zeros((2, 3)))
