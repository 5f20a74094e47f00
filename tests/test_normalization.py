"""Normalization: openpi's formulas on the fixture stats, the near-constant guard, files, streaming statistics."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch

from pi0_torch.processing.normalization import (
    NormStats,
    RunningStats,
    apply_delta,
    compute_norm_stats,
    degenerate_dims,
    load_openpi_norm_stats,
    normalize,
    save_openpi_norm_stats,
    unnormalize,
)

from conftest import FIXTURES

STATS_DIR = FIXTURES / "pi0_small" / "ckpt" / "0"


@pytest.fixture(scope="module")
def stats() -> dict[str, NormStats]:
    return load_openpi_norm_stats(STATS_DIR)


def test_load_fixture_stats(stats: dict[str, NormStats]) -> None:
    raw = json.loads((STATS_DIR / "assets" / "reference" / "norm_stats.json").read_text())["norm_stats"]
    assert sorted(stats) == ["actions", "state"]
    for key in stats:
        assert stats[key].dim == 8
        for field in ("mean", "std", "q01", "q99"):
            np.testing.assert_array_equal(getattr(stats[key], field), raw[key][field])
    # the same file found three ways
    for path in (STATS_DIR / "assets" / "reference", STATS_DIR / "assets" / "reference" / "norm_stats.json"):
        np.testing.assert_array_equal(load_openpi_norm_stats(path)["state"].mean, stats["state"].mean)


@pytest.mark.parametrize("key", ["state", "actions"])
def test_openpi_formulas_on_fixture_stats(stats: dict[str, NormStats], key: str) -> None:
    s = stats[key]
    x = np.random.default_rng(0).normal(size=(5, 8)) * 2  # float64 like openpi's numpy pipeline
    z = normalize(x, s, "zscore")
    np.testing.assert_array_equal(z, (x - s.mean) / (s.std + 1e-6))  # bit-exact: same formula, same order
    q = normalize(x, s, "quantile")
    np.testing.assert_array_equal(q, (x - s.q01) / (s.q99 - s.q01 + 1e-6) * 2.0 - 1.0)
    np.testing.assert_array_equal(unnormalize(z, s, "zscore"), z * (s.std + 1e-6) + s.mean)
    np.testing.assert_array_equal(unnormalize(q, s, "quantile"), (q + 1.0) / 2.0 * (s.q99 - s.q01 + 1e-6) + s.q01)
    for mode in ("zscore", "quantile", "none"):
        np.testing.assert_allclose(unnormalize(normalize(x, s, mode), s, mode), x, rtol=0, atol=1e-12)


def test_torch_and_float32(stats: dict[str, NormStats]) -> None:
    s = stats["actions"]
    x = np.random.default_rng(1).normal(size=(2, 50, 8)).astype(np.float32)
    for mode in ("zscore", "quantile"):
        expected = normalize(x.astype(np.float64), s, mode)
        out_np = normalize(x, s, mode)
        assert out_np.dtype == np.float32 and np.allclose(out_np, expected, atol=1e-5)
        out_t = normalize(torch.from_numpy(x), s, mode)
        assert isinstance(out_t, torch.Tensor) and out_t.dtype == torch.float32
        assert np.allclose(out_t.numpy(), expected, atol=1e-5)
        back = unnormalize(out_t, s, mode)
        assert torch.allclose(back, torch.from_numpy(x), atol=1e-5)
        assert normalize(torch.from_numpy(x).double(), s, mode).dtype == torch.float64


def test_near_constant_dims_are_floored_not_exploded() -> None:
    # dim 0 constant (std 0, q01 == q99 == 0.5), dim 1 ordinary
    s = NormStats(mean=[0.5, 0.0], std=[0.0, 1.0], q01=[0.5, -2.0], q99=[0.5, 2.0])
    assert degenerate_dims(s, "zscore") == [0] and degenerate_dims(s, "quantile") == [0]
    assert degenerate_dims(s, "zscore", min_scale=0) == []
    x = np.array([[0.5, 1.0], [0.51, 1.0]])  # the constant value, then a deviation of 0.01
    for mode, at_constant in (("zscore", 0.0), ("quantile", -1.0)):
        guarded = normalize(x, s, mode)
        openpi = normalize(x, s, mode, min_scale=0)
        # the training value maps exactly as in openpi; the ordinary dim is untouched
        assert guarded[0, 0] == openpi[0, 0] == at_constant
        np.testing.assert_array_equal(guarded[:, 1], openpi[:, 1])
        # a 0.01 deviation: openpi ~1e4, guarded bounded by 0.01 / 1e-3 (x2 for quantile)
        assert abs(openpi[1, 0]) > 5e3 and abs(guarded[1, 0] - at_constant) <= 20.0 + 1e-6
        np.testing.assert_allclose(unnormalize(guarded, s, mode), x, atol=1e-12)
        # model outputs near the training value stay near the constant in robot units
        assert abs(unnormalize(np.array([[at_constant + 0.1, 0.0]]), s, mode)[0, 0] - 0.5) < 1e-3


def test_norm_stats_validation() -> None:
    with pytest.raises(ValueError, match="one length"):
        NormStats(mean=[0, 0], std=[1])
    with pytest.raises(ValueError, match="NaN or inf"):
        NormStats(mean=[np.nan], std=[1])
    with pytest.raises(ValueError, match="std must be >= 0"):
        NormStats(mean=[0], std=[-1])
    with pytest.raises(ValueError, match="q99 must be >= q01"):
        NormStats(mean=[0], std=[1], q01=[1], q99=[0])
    with pytest.raises(ValueError, match="given together"):
        NormStats(mean=[0], std=[1], q01=[0])
    with pytest.raises(ValueError, match="non-empty 1-D"):
        NormStats(mean=[[0]], std=[[1]])
    s = NormStats(mean=[0, 1, 2], std=[1, 1, 1])
    with pytest.raises(ValueError, match="quantile normalization needs q01 and q99"):
        normalize(np.zeros(3), s, "quantile")
    with pytest.raises(ValueError, match="last dim of the values is 2, the norm stats have 3"):
        normalize(np.zeros(2), s, "zscore")
    with pytest.raises(ValueError, match="norm_mode must be one of"):
        normalize(np.zeros(3), s, "minmax")
    assert s.truncated(2).mean.tolist() == [0, 1] and s.truncated(2).q01 is None
    with pytest.raises(ValueError, match="cannot take the first 4"):
        s.truncated(4)


def test_save_load_roundtrip_in_openpi_layout(stats: dict[str, NormStats], tmp_path) -> None:
    extra = {**stats, "mean_only": NormStats(mean=[1.0], std=[2.0])}
    path = save_openpi_norm_stats(tmp_path / "assets" / "robot", extra)
    assert path == tmp_path / "assets" / "robot" / "norm_stats.json"
    raw = json.loads(path.read_text())
    assert set(raw) == {"norm_stats"} and set(raw["norm_stats"]["state"]) == {"mean", "std", "q01", "q99"}
    assert raw["norm_stats"]["mean_only"]["q01"] is None
    loaded = load_openpi_norm_stats(tmp_path)  # a step folder: finds assets/<id>/norm_stats.json
    for key, value in extra.items():
        for field in ("mean", "std", "q01", "q99"):
            a, b = getattr(value, field), getattr(loaded[key], field)
            assert (a is None and b is None) or np.array_equal(a, b)
    assert not list(tmp_path.rglob("*.tmp"))


def test_load_errors(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="expected one norm_stats.json"):
        load_openpi_norm_stats(tmp_path)
    for asset in ("a", "b"):
        save_openpi_norm_stats(tmp_path / "assets" / asset, {"state": NormStats(mean=[0], std=[1])})
    with pytest.raises(FileNotFoundError, match="found: .*assets/a/norm_stats.json.*assets/b/norm_stats.json"):
        load_openpi_norm_stats(tmp_path)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"state": {"mean": [0], "std": [1]}}))
    with pytest.raises(ValueError, match="openpi's layout"):
        load_openpi_norm_stats(bad)
    bad.write_text(json.dumps({"norm_stats": {"state": {"mean": [0]}}}))
    with pytest.raises(ValueError, match=r"lacks \['std'\]"):
        load_openpi_norm_stats(bad)


def _samples(n: int, seed: int = 0) -> list[dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    return [{"state": rng.normal(1.0, 2.0, size=5), "actions": rng.gamma(2.0, size=(10, 3))} for _ in range(n)]


def test_compute_exact_small() -> None:
    samples = _samples(300)
    stats = compute_norm_stats(samples, progress=False)
    states = np.stack([s["state"] for s in samples])
    actions = np.concatenate([s["actions"] for s in samples])
    for key, values in (("state", states), ("actions", actions)):
        np.testing.assert_allclose(stats[key].mean, values.mean(0), rtol=1e-12)
        np.testing.assert_allclose(stats[key].std, values.std(0), rtol=1e-10)
        np.testing.assert_allclose(stats[key].q01, np.quantile(values, 0.01, axis=0), rtol=1e-12)
        np.testing.assert_allclose(stats[key].q99, np.quantile(values, 0.99, axis=0), rtol=1e-12)
    # torch tensors, batched items and a generator give the same numbers
    batched = (
        {k: torch.from_numpy(np.stack([s[k] for s in samples[i : i + 7]])) for k in ("state", "actions")}
        for i in range(0, 300, 7)
    )
    again = compute_norm_stats(batched, progress=False)
    for key in ("state", "actions"):
        np.testing.assert_allclose(again[key].mean, stats[key].mean, rtol=1e-12)
        np.testing.assert_allclose(again[key].q99, stats[key].q99, rtol=1e-12)
    single = compute_norm_stats((s["state"] for s in samples), progress=False)
    assert isinstance(single, NormStats) and np.allclose(single.mean, stats["state"].mean)


def test_histogram_quantiles_like_openpi() -> None:
    # Past max_exact_rows the quantiles come from openpi's growing 5000-bin histogram (ranges grow batch by batch).
    rng = np.random.default_rng(3)
    batches = [rng.normal(0, 1 + i, size=(500, 4)) for i in range(6)]
    values = np.concatenate(batches)
    running = RunningStats(max_exact_rows=100)
    for batch in batches:
        running.update(batch)
    assert not running.uses_exact_quantiles
    stats = running.get_statistics()
    value_range = values.max(0) - values.min(0)
    for q, got in ((0.01, stats.q01), (0.99, stats.q99)):
        exact = np.quantile(values, q, axis=0)
        # openpi's estimate drifts low by up to a bin per range growth (5 growths here): measured <= 0.3% of the range
        assert np.all(np.abs(got - exact) <= 0.005 * value_range), (got, exact)
    np.testing.assert_allclose(stats.mean, values.mean(0), rtol=1e-12)  # mean/std stay exact
    np.testing.assert_allclose(stats.std, values.std(0), rtol=1e-10)
    # a single batch: the quantile is the left edge of the first bin whose cumulative count reaches q * n
    one = RunningStats(max_exact_rows=0)
    data = np.arange(1000, dtype=np.float64)[:, None]
    one.update(data)
    edges = np.linspace(-1e-10, 999 + 1e-10, 5001)
    cumulative = np.cumsum(np.histogram(data[:, 0], bins=edges)[0])
    assert one.get_statistics().q01[0] == edges[np.searchsorted(cumulative, 10.0)]


def test_compute_with_delta_actions() -> None:
    samples = _samples(50)
    mask = [True, False]
    stats = compute_norm_stats(samples, delta_action_mask=mask, progress=False)
    deltas = np.concatenate([s["actions"] - np.array([s["state"][0], 0.0, 0.0]) for s in samples])
    np.testing.assert_allclose(stats["actions"].mean, deltas.mean(0), rtol=1e-12)


def test_compute_warns_on_constant_dims() -> None:
    samples = [{"state": np.array([float(i), 1.0]), "actions": np.array([[float(i), 0.0]])} for i in range(10)]
    with pytest.warns(UserWarning) as record:
        compute_norm_stats(samples, progress=False)
    messages = sorted(str(w.message) for w in record)
    assert len(messages) == 2
    assert messages[0].startswith("norm stats 'actions': (near) constant dims (scale < 0.001): [1] by std, [1] by q99 - q01")
    assert messages[1].startswith("norm stats 'state': (near) constant dims (scale < 0.001): [1] by std, [1] by q99 - q01")


def test_compute_errors() -> None:
    with pytest.raises(ValueError, match="got no samples"):
        compute_norm_stats([], progress=False)
    with pytest.raises(ValueError, match=r"sample 1: missing keys \['actions'\]"):
        compute_norm_stats([{"state": [0.0], "actions": [[0.0]]}, {"state": [0.0]}], progress=False)
    with pytest.raises(ValueError, match="NaN or inf"):
        compute_norm_stats([np.array([0.0, np.nan]), np.array([1.0, 1.0])], progress=False)
    with pytest.raises(ValueError, match="at least 2 vectors"):
        compute_norm_stats([np.array([0.0, 1.0])], progress=False)
    with pytest.raises(ValueError, match="vectors of length 3 after vectors of length 2"):
        compute_norm_stats([np.zeros(2), np.zeros(3)], progress=False)
    with pytest.raises(ValueError, match="a plain array after dicts"):
        compute_norm_stats([{"state": [0.0], "actions": [[0.0]]}, np.zeros(1)], progress=False)
    with pytest.raises(ValueError, match="expected a numeric array, got dtype <U1"):
        compute_norm_stats([np.array(["a"])], progress=False)


def test_apply_delta_roundtrip() -> None:
    rng = np.random.default_rng(0)
    actions, state = rng.normal(size=(2, 4, 3)), rng.normal(size=(2, 5))
    mask = [True, False]  # shorter than both: dim 2 stays absolute
    delta = apply_delta(actions, state, mask)
    np.testing.assert_array_equal(delta[..., 0], actions[..., 0] - state[:, None, 0])
    np.testing.assert_array_equal(delta[..., 1:], actions[..., 1:])
    np.testing.assert_allclose(apply_delta(delta, state, mask, inverse=True), actions, atol=1e-15)
    delta_t = apply_delta(torch.from_numpy(actions), torch.from_numpy(state), mask)
    np.testing.assert_allclose(delta_t.numpy(), delta)
    with pytest.raises(ValueError, match="delta_action_mask has 4 entries"):
        apply_delta(actions, state, [True] * 4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        apply_delta(actions[0], state[0], mask)  # unbatched [H, D] with [D]
