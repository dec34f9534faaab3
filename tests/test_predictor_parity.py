"""The flax GST matches the released PyTorch model's outputs (through CrowdNav++'s inference wrapper) on the
reference fixture, edge cases included, to 1e-4 m and 1e-4 (sigma, rho)."""

import pathlib

import jax
import numpy as np
import pytest

from tgrf_jax.env import gst as predictor

# CrowdNav++'s released GST weights and the PyTorch model's outputs: tests/data/gst_reference/README.md
FIXTURE = pathlib.Path(__file__).resolve().parent / "data" / "gst_reference" / "gst_reference.npz"
BATCHES = ("", "_1", "_2", "_env15", "_allinv", "_single")
TOL = 1e-4


@pytest.fixture(scope="module")
def ref():
    with np.load(FIXTURE) as data:
        return {k: data[k] for k in data.files}


@pytest.fixture(scope="module")
def params(ref):
    return predictor.from_torch_state_dict({k: v for k, v in ref.items() if k.startswith("w/")})


@pytest.fixture(scope="module")
def fns():
    return (
        jax.jit(jax.vmap(predictor.predict, in_axes=(None, 0, 0))),
        jax.jit(jax.vmap(predictor.step_gaussians, in_axes=(None, 0, 0))),
    )


def test_state_dict_names_with_or_without_prefix(ref, params):
    bare = predictor.from_torch_state_dict({k[2:]: v for k, v in ref.items() if k.startswith("w/")})
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(bare)):
        np.testing.assert_array_equal(a, b)
    # The reference's parameters, less one of the two LSTM bias vectors (256 each, summed into one here), plus the
    # constant-velocity prior, which is off: one scalar, with its 2 x 64 raw-displacement map.
    reference = sum(v.size for k, v in ref.items() if k.startswith("w/"))
    assert sum(x.size for x in jax.tree_util.tree_leaves(params)) == reference - 256 + 1 + 128
    assert float(params["cv_prior"]) == 0.0 and not np.any(params["speed"]["kernel"])


def test_bad_state_dict_names_the_key(ref):
    arrays = {k: v for k, v in ref.items() if k.startswith("w/") and "hidden2pos.bias" not in k}
    with pytest.raises(predictor.WeightsError, match="hidden2pos.bias"):
        predictor.from_torch_state_dict(arrays)


@pytest.mark.parametrize("batch", BATCHES)
def test_matches_reference(ref, params, fns, batch):
    predict, raw = fns
    traj, mask = ref["in_traj" + batch], ref["in_mask" + batch][..., 0] > 0.5
    out, steps = predict(params, traj, mask), raw(params, traj, mask)
    out_mask = ref["out_mask" + batch][..., 0] > 0.5
    np.testing.assert_array_equal(np.asarray(out.out_mask), out_mask)
    expected = ref["out_traj" + batch]
    means = np.asarray(out.means)
    np.testing.assert_allclose(means[out_mask], expected[..., :2][out_mask], atol=TOL, rtol=0)
    # Humans without a prediction hold their last observed position (the env's "stationary" slots).
    np.testing.assert_array_equal(means[~out_mask], np.repeat(traj[:, :, -1:], 5, 2)[~out_mask])
    np.testing.assert_allclose(np.asarray(out.sigmas), expected[..., 2:4], atol=TOL, rtol=0)
    np.testing.assert_allclose(np.asarray(out.rho), expected[..., 4], atol=TOL, rtol=0)
    per_step = lambda x: np.swapaxes(np.asarray(x), 1, 2)  # (env, human, k) -> (env, k, human)
    np.testing.assert_allclose(per_step(steps.mu), ref["raw_mu" + batch], atol=TOL, rtol=0)
    np.testing.assert_allclose(per_step(steps.sigma[..., 0]), ref["raw_sx" + batch][..., 0], atol=TOL, rtol=0)
    np.testing.assert_allclose(per_step(steps.sigma[..., 1]), ref["raw_sy" + batch][..., 0], atol=TOL, rtol=0)
    np.testing.assert_allclose(per_step(steps.corr), ref["raw_corr" + batch][..., 0], atol=TOL, rtol=0)
    for leaf in jax.tree_util.tree_leaves((out, steps)):
        assert np.all(np.isfinite(np.asarray(leaf)))


def test_filler_enters_through_the_displacement_quirk(ref, params, fns):
    """Batch 0 and `_env15` differ only in the filler of unseen frames; the reference's mask quirk lets it
    shift predictions, and the port must shift them the same way (not mask the filler out)."""
    predict, _ = fns
    a = predict(params, ref["in_traj"], ref["in_mask"][..., 0] > 0.5)
    b = predict(params, ref["in_traj_env15"], ref["in_mask_env15"][..., 0] > 0.5)
    om = np.asarray(a.out_mask)
    assert np.abs(np.asarray(a.means) - np.asarray(b.means))[om].max() > 1e-2
