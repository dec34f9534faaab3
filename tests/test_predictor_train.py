"""Predictor data, loss, training (bit-identical resume), evaluation and the `tgrf-predictor` command."""

import dataclasses
import json
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax.cli import predictor as cli
from tgrf_jax.env import gst as predictor
from tgrf_jax.env.gst.model import StepGaussians, step_gaussians
from tgrf_jax.predictor import data as data_lib
from tgrf_jax.predictor import train as train_lib


def synthetic(b=5, t=40, n=3, seed=0):
    """Straight-line walkers seen all the time, except human 2 who leaves the view for frames 12..14."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(-3, 3, (b, 1, n, 2))
    vel = rng.uniform(-1, 1, (b, 1, n, 2))
    times = np.arange(t, dtype=np.float32)[None, :, None, None] * 0.25
    visible = np.ones((b, t, n), bool)
    visible[:, 12:15, 2] = False
    seg = np.zeros((b, t, n), np.int16)
    seg[:, 15:, 2] = 1  # re-entry: a new pedestrian
    arrays = dict(
        robot_pos=np.zeros((b, t, 2), np.float32),
        human_pos=(start + vel * times).astype(np.float32),
        visible=visible,
        seg=seg,
    )
    return {"arrays": arrays, "config": {"crowd": "synthetic", "seed": seed}}


def test_window_rules():
    arrays = synthetic()["arrays"]
    index = data_lib.window_index(arrays["visible"], arrays["seg"], range(1))
    # humans 0 and 1 are present throughout, so every start is kept
    assert len(index) == 40 - 9
    arrays["visible"][0, :, :2] = False
    index = data_lib.window_index(arrays["visible"], arrays["seg"], range(1))
    # only human 2 left: windows must lie inside frames 0..11 or 15..39
    assert set(index[:, 1].tolist()) == set(range(0, 3)) | set(range(15, 31))
    train, val = data_lib.split_index(synthetic()["arrays"])
    assert set(train[:, 0].tolist()) == {0, 1, 2, 3} and set(val[:, 0].tolist()) == {4}


def test_reentry_is_a_new_pedestrian():
    arrays = synthetic()["arrays"]
    data = data_lib.device_arrays(arrays)
    w = data_lib.make_window(data, jnp.array([0, 10]))  # frames 10..19; human 2 unseen in 12..14, new id from 15
    # the observed pedestrian (seen in frames 10, 11) is gone; the one entering at 15 is someone else
    np.testing.assert_array_equal(np.asarray(w.visible[2]), [True, True, False, False, False])
    np.testing.assert_array_equal(np.asarray(w.target_valid[2]), [False] * 5)
    np.testing.assert_allclose(np.asarray(w.positions[2, 2:]), np.full((3, 2), 15.0))  # the env's filler
    w = data_lib.make_window(data, jnp.array([0, 13]))  # frames 13..22: seen from frame 15 (observed index 2)
    np.testing.assert_array_equal(np.asarray(w.visible[2]), [False, False, True, True, True])
    np.testing.assert_array_equal(np.asarray(w.target_valid[2]), [True] * 5)
    np.testing.assert_allclose(np.asarray(w.target[0]), arrays["human_pos"][0, 18:23, 0])


def test_nll_is_the_bivariate_gaussian_density():
    rng = np.random.default_rng(1)
    mu, sig = rng.normal(size=(4, 5, 2)) * 0.1, rng.uniform(0.05, 0.5, (4, 5, 2))
    corr = rng.uniform(-0.9, 0.9, (4, 5))
    g = StepGaussians(mu=jnp.asarray(mu), sigma=jnp.asarray(sig), corr=jnp.asarray(corr), out_mask=jnp.ones(4, bool))
    pos = rng.normal(size=(4, 5, 2))
    target = pos[:, -1:] + np.cumsum(rng.normal(size=(4, 5, 2)) * 0.2, axis=1)
    batch = data_lib.Batch(
        positions=jnp.asarray(pos),
        visible=jnp.ones((4, 5), bool),
        target=jnp.asarray(target),
        target_valid=jnp.ones((4, 5), bool),
    )
    nll, mask = train_lib.nll_terms(g, batch)
    disp = np.diff(np.concatenate([pos[:, -1:], target], 1), axis=1)
    for i, k in [(0, 0), (2, 3), (3, 4)]:
        sx, sy, r = sig[i, k, 0], sig[i, k, 1], corr[i, k]
        cov = np.array([[sx * sx, r * sx * sy], [r * sx * sy, sy * sy]])
        d = disp[i, k] - mu[i, k]
        logpdf = -0.5 * d @ np.linalg.solve(cov, d) - 0.5 * np.log(np.linalg.det(cov)) - np.log(2 * np.pi)
        np.testing.assert_allclose(float(nll[i, k]), -(logpdf + np.log(2 * np.pi)), rtol=1e-4)
    assert bool(mask.all())


def test_ade_mean_loss_fits_means_by_distance_and_spreads_by_nll():
    data = data_lib.device_arrays(synthetic()["arrays"])
    batch = jax.vmap(lambda es: data_lib.make_window(data, es))(jnp.array([[0, 3], [1, 20], [2, 5]]))
    rng = np.random.default_rng(0)
    mu = jnp.asarray(rng.normal(size=(3, 3, 5, 2)) * 0.1, jnp.float32)

    def g(sigma):
        return StepGaussians(
            mu=mu, sigma=jnp.full((3, 3, 5, 2), sigma), corr=jnp.zeros((3, 3, 5)), out_mask=jnp.ones((3, 3), bool)
        )

    mean_grad = lambda sigma, mean_loss: np.asarray(
        jax.grad(lambda m: train_lib.gaussians_loss(g(sigma).replace(mu=m), batch, mean_loss))(mu)
    )
    # under "ade" the pull on the means does not depend on the predicted spread; under the NLL it does
    np.testing.assert_allclose(mean_grad(0.05, "ade"), mean_grad(1.0, "ade"), rtol=1e-6)
    assert np.abs(mean_grad(0.05, "ade")).max() > 0
    assert not np.allclose(mean_grad(0.05, "nll"), mean_grad(1.0, "nll"), rtol=1e-2)
    # and it is the mean Euclidean error of the predicted positions over the valid steps
    nll_only = train_lib.gaussians_loss(g(1.0).replace(mu=jax.lax.stop_gradient(mu)), batch, "nll")
    means = batch.positions[:, :, -1:] + np.cumsum(np.asarray(mu), axis=2)
    mask = np.asarray(batch.target_valid)
    ade = np.linalg.norm(means - np.asarray(batch.target), axis=-1)[mask].mean()
    np.testing.assert_allclose(float(train_lib.gaussians_loss(g(1.0), batch, "ade")), float(nll_only) + ade, rtol=1e-5)
    with pytest.raises(ValueError, match="mean_loss = 'mse'.*ade, nll"):
        train_lib.TrainConfig(mean_loss="mse")


def test_ade_loss_shapes_the_network_by_position_error_only():
    """Under "ade" the spreads' NLL trains only the head's spread rows; the forward pass is unchanged."""
    data = data_lib.device_arrays(synthetic()["arrays"])
    batch = jax.vmap(lambda es: data_lib.make_window(data, es))(jnp.array([[0, 3], [1, 20], [2, 5]]))
    params = jax.jit(lambda: train_lib.init_state(train_lib.TrainConfig(cv_prior=True)).params)()
    params = {**params, "head": jax.tree_util.tree_map(lambda x: x + 0.01, params["head"])}  # off the prior

    @jax.jit  # one program for both variants: run eagerly, every op is a program of its own
    def forward_and_spread_grads(p):
        out = {}
        for detach in (True, False):
            model = lambda q, detach=detach: jax.vmap(  # (a one-line model per variant)
                lambda b: step_gaussians(q, b.positions, b.visible, detach_spreads=detach)
            )(batch)
            spread_loss = lambda q, model=model: train_lib.gaussians_loss(  # (as the model)
                model(q).replace(mu=jnp.zeros((3, 3, 5, 2))), batch, "nll"
            )
            out[detach] = (model(p), jax.grad(spread_loss)(p))
        return out

    out = forward_and_spread_grads(params)
    (g_detached, detached), (g_attached, attached) = out[True], out[False]
    for a, b in zip(jax.tree_util.tree_leaves(g_detached), jax.tree_util.tree_leaves(g_attached)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert all(not np.any(np.asarray(x)) for x in jax.tree_util.tree_leaves(detached["lstm"]))
    assert any(np.any(np.asarray(x)) for x in jax.tree_util.tree_leaves(attached["lstm"]))
    assert np.any(np.asarray(detached["head"]["kernel"][:, 2:])) and not np.any(detached["head"]["kernel"][:, :2])
    with pytest.raises(ValueError, match="dropout = 1.0 must be in"):
        train_lib.TrainConfig(dropout=1.0)


def test_constant_velocity_is_exact_on_straight_walkers():
    dataset = synthetic()
    data = data_lib.device_arrays(dataset["arrays"])
    _, val = data_lib.split_index(dataset["arrays"])
    evaluate = train_lib.make_evaluator(data, chunk=8)
    # initialisations jitted: run eagerly, each initialiser of each layer shape is a program of its own
    metrics = evaluate(jax.jit(predictor.init_params)(jax.random.key(0)), val)
    assert metrics["cv_ade"] < 1e-5 and metrics["cv_fde"] < 1e-5
    assert metrics["ade"] > 0.01 and np.isfinite(metrics["nll"])
    assert metrics["windows"] == len(val)
    # with the constant-velocity prior, the untrained model (zero head) is constant velocity
    prior = evaluate(jax.jit(lambda: train_lib.init_state(train_lib.TrainConfig(cv_prior=True)).params)(), val)
    assert prior["ade"] < 1e-5 and prior["humans"] == metrics["humans"]
    assert metrics["ade_change"] > 1 and metrics["ade_change_ci95"][0] <= metrics["ade_change"]
    assert metrics["episodes"] == len(np.unique(val[:, 0]))


def test_relative_change_resamples_whole_episodes():
    episode = np.repeat(np.arange(10), 30)
    cv = np.random.default_rng(1).uniform(0.5, 1.5, len(episode))
    # every episode 10% better: the interval has no width, whatever the windows' spread
    change, ci = train_lib.relative_change(0.9 * cv, cv, episode)
    assert change == pytest.approx(-0.1) and ci == pytest.approx([-0.1, -0.1])
    # half the episodes 30% better, half equal: the ratio of sums, inside an interval as wide as the episodes'
    # disagreement (windows of one episode do not count as independent evidence)
    model = np.where(episode < 5, 0.7, 1.0) * cv
    change, (lo, hi) = train_lib.relative_change(model, cv, episode)
    assert change == pytest.approx(model.sum() / cv.sum() - 1)
    assert lo < change < hi and hi - lo > 0.1 and hi < 0
    assert train_lib.relative_change(model, cv, episode) == (change, [lo, hi])  # fixed seed


def test_training_resumes_bit_identically(tmp_path):
    dataset = synthetic()
    config = train_lib.TrainConfig(
        updates=4, batch_size=4, log_every=2, checkpoint_every=2, decay_every=2, eval_windows=8, dropout=0.1
    )  # dropout: its keys must resume too
    full, meta = train_lib.train(config, dataset, tmp_path / "full", log=lambda s: None)
    assert meta["eval"]["humans"] > 0
    # stop after 2 updates, then resume the same run to 4 (the update count may grow between invocations)
    half = train_lib.TrainConfig(**{**meta["train"], "updates": 2})
    train_lib.train(half, dataset, tmp_path / "split", log=lambda s: None)
    resumed, _ = train_lib.train(config, dataset, tmp_path / "split", log=lambda s: None)
    for a, b in zip(jax.tree_util.tree_leaves(full), jax.tree_util.tree_leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # a run directory holding another config is refused, naming the directory
    with pytest.raises(train_lib.CheckpointError, match="split.*batch_size"):
        train_lib.train(train_lib.TrainConfig(**{**meta["train"], "batch_size": 8}), dataset, tmp_path / "split")


def test_dataset_roundtrip_and_errors(tmp_path):
    dataset = synthetic()
    path = data_lib.save_dataset(tmp_path / "d.npz", dataset)
    loaded = data_lib.load_dataset(path)
    for k, v in dataset["arrays"].items():
        np.testing.assert_array_equal(loaded["arrays"][k], v)
    assert json.loads((tmp_path / "d.json").read_text())["config"] == dataset["config"]
    with pytest.raises(data_lib.DatasetError, match="missing.npz.*does not exist"):
        data_lib.load_dataset(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(data_lib.DatasetError, match="bad.npz.*corrupt"):
        data_lib.load_dataset(bad)


def test_collector_is_deterministic_and_logs_only_what_the_robot_sees():
    config = data_lib.CollectConfig(crowd="social_force", num_envs=5, steps=12, num_humans=4, chunk=6, seed=3)
    a = data_lib.collect(config, log=lambda s: None)["arrays"]
    b = data_lib.collect(config, log=lambda s: None)["arrays"]
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert a["human_pos"].shape == (5, 12, 4, 2)
    # visibility is the 5 m edge-to-edge sensor: centre distance <= 5 + 0.3 + r (r <= 0.5)
    dist = np.linalg.norm(a["human_pos"] - a["robot_pos"][:, :, None], axis=-1)
    assert np.all(dist[a["visible"]] <= 5.8 + 1e-5) and np.all(dist[~a["visible"]] > 5.6 - 1e-5)
    # a slot's segment advances exactly when its human comes (back) into view or respawns
    assert np.all(np.diff(a["seg"].astype(int), axis=1) >= 0)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["train", "--dataset", "nowhere.npz", "--run-dir", "r"], "nowhere.npz.*does not exist"),
        (["train", "--dataset", "d.npz", "--run-dir", "r", "--updates", "0"], "updates = 0 must be an integer >= 1"),
        (["train", "--dataset", "d.npz", "--run-dir", "r", "--mean-loss", "mse"], "--mean-loss: invalid choice"),
        (["train", "--dataset", "d.npz", "--run-dir", "r", "--dropout", "-0.1"], "dropout = -0.1 must be in"),
        (["collect", "--envs", "2", "--out", "x.npz"], "num_envs = 2 must be an integer >= 5"),
        (["eval", "--dataset", "d.npz", "--params", "nothing.npz"], "nothing.npz.*do not exist"),
        (["collect", "--recordings", "zara9", "--out", "x.npz"], "--recordings 'zara9' is not a catalogue name"),
        (["collect", "--recordings", "zara1", "--out", "x.npz"], "--recordings: 1 file.*tgrf-data fetch eth-ucy"),
    ],
)
def test_cli_errors_name_the_option_or_path(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    try:
        code = cli.main(argv)
    except SystemExit as e:  # argparse's own errors (an unknown choice) exit
        code = e.code
    assert code == 2
    assert re.search(message, capsys.readouterr().err)


def test_cli_rejects_parameters_that_do_not_fit(tmp_path, capsys):
    np.savez(tmp_path / "p.npz", **{"head/kernel": np.zeros((64, 5))})
    data_lib.save_dataset(tmp_path / "d.npz", synthetic())
    assert cli.main(["eval", "--dataset", str(tmp_path / "d.npz"), "--params", str(tmp_path / "p.npz")]) == 2
    err = capsys.readouterr().err
    assert "p.npz" in err and "do not fit the GST model" in err


def test_a_run_is_resumed_only_as_itself(tmp_path):
    """--updates below the run's progress, another dataset with the same recorded config, a second writer and a
    directory of another tool are refused before anything is written; --from-step goes back to a checkpoint."""
    from tgrf_jax.config import ConfigError
    from tgrf_jax.storage.lock import exclusive

    dataset = synthetic()
    config = train_lib.TrainConfig(
        updates=4, batch_size=4, log_every=2, checkpoint_every=2, decay_every=2, eval_windows=8
    )
    run = tmp_path / "run"
    full, _ = train_lib.train(config, dataset, run, log=lambda s: None)
    run_json = (run / "run.json").read_text()
    short = train_lib.TrainConfig(**{**dataclasses.asdict(config), "updates": 2})
    with pytest.raises(
        train_lib.CheckpointError,
        match=r"--updates 2 is below the progress of .*run': its checkpoint "
        r"of update 4 would be labelled 2; .*--from-step N",
    ):
        train_lib.train(short, dataset, run, log=lambda s: None)
    # --from-step 2 goes back: the run trained to 2 again, labelled 2, the later checkpoint deleted
    two, meta = train_lib.train(short, dataset, run, log=lambda s: None, from_step=2)
    assert meta["train"]["updates"] == 2 and sorted(p.name for p in (run / "checkpoints").iterdir()) == ["2"]
    again, _ = train_lib.train(config, dataset, run, log=lambda s: None)  # and on to 4, as the first time
    for a, b in zip(jax.tree_util.tree_leaves(full), jax.tree_util.tree_leaves(again)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    other = synthetic(seed=1)
    other["config"] = dataset["config"]  # same recorded config, other content
    with pytest.raises(train_lib.CheckpointError, match=r"was trained on another dataset \(content SHA-256"):
        train_lib.train(config, other, run, log=lambda s: None)
    with exclusive(run):
        with pytest.raises(ConfigError, match=r"is being written by another process"):
            train_lib.train(config, dataset, run, log=lambda s: None)
    assert (run / "run.json").read_text().replace('"updates": 2', '"updates": 4') == run_json

    train_run = tmp_path / "train_run"  # what tgrf-train leaves
    (train_run / "checkpoints").mkdir(parents=True)
    (train_run / "config.yaml").write_text("ppo: {}\n")
    with pytest.raises(
        train_lib.CheckpointError,
        match=r"holds config.yaml but no run.json: it is not a "
        r"tgrf-predictor run directory",
    ):
        train_lib.train(config, dataset, train_run, log=lambda s: None)
    assert sorted(p.name for p in train_run.iterdir()) == ["checkpoints", "config.yaml"]


def test_a_non_finite_loss_stops_training_and_keeps_the_checkpoints(tmp_path, monkeypatch):
    dataset = synthetic()
    config = train_lib.TrainConfig(
        updates=6, batch_size=4, log_every=2, checkpoint_every=2, decay_every=2, eval_windows=8
    )
    real = train_lib.train_chunk

    def diverging(state, data, index, config, length):
        state, loss = real(state, data, index, config, length)
        return state, loss if int(state.step) < 4 else jnp.float32(np.nan)

    monkeypatch.setattr(train_lib, "train_chunk", diverging)
    with pytest.raises(
        train_lib.TrainingError,
        match=r"the training loss is nan in the updates 3..4: .* the "
        r"checkpoints up to update 2 in .* are kept",
    ):
        train_lib.train(config, dataset, tmp_path / "run", log=lambda s: None)
    assert sorted(p.name for p in (tmp_path / "run" / "checkpoints").iterdir()) == ["2"]


def test_cli_from_step_continues_from_that_checkpoint(tmp_path, capsys):
    """`tgrf-predictor train --from-step N`, from the command line to the resumed training: it restores checkpoint
    N (not the latest), deletes the later ones and trains their updates again, bit-identically; a step with no
    intact checkpoint is one line of error."""
    from helpers import flip_a_bit

    data_lib.save_dataset(tmp_path / "d.npz", synthetic())
    run = tmp_path / "run"
    argv = [
        "train",
        "--dataset",
        str(tmp_path / "d.npz"),
        "--run-dir",
        str(run),
        "--updates",
        "4",
        "--batch-size",
        "4",
        "--log-every",
        "2",
        "--checkpoint-every",
        "2",
        "--decay-every",
        "2",
        "--eval-windows",
        "8",
    ]

    def train(*extra):
        return cli.main(argv + list(extra)), capsys.readouterr()

    def params():
        with np.load(run / "gst.npz") as f:
            return {k: f[k] for k in f.files}

    assert train()[0] == 0
    first = params()
    code, out = train("--from-step", "2")
    assert code == 0, out.err
    assert f"resumed from {run / 'checkpoints'} at update 2" in out.out
    assert "update      4/4" in out.out and "update      2/4" not in out.out  # updates 3-4 only, trained again
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["2", "4"]
    assert json.loads((run / "run.json").read_text())["train"]["updates"] == 4
    again = params()
    assert again.keys() == first.keys()
    for k in first:
        np.testing.assert_array_equal(again[k], first[k])

    for step, message in [
        ("3", (f"--from-step 3: {str(run / 'checkpoints')!r} holds no checkpoint of update 3; it holds: 2, 4")),
        ("2", f"checkpoint {str(run / 'checkpoints' / '2')!r} (step 2) is damaged"),
    ]:
        if step == "2":
            flip_a_bit(run / "checkpoints" / "2")
        code, out = train("--from-step", step)
        assert code == 2
        assert out.err.startswith("tgrf-predictor: error: ") and message in out.err, out.err
        assert len(out.err.splitlines()) == 1 and "Traceback" not in out.err, out.err
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["2", "4"]  # nothing deleted by a refusal


def test_a_dataset_from_recordings_reads_as_a_simulated_one(tmp_path, monkeypatch, capsys):
    from helpers import write_catalogue_recordings

    write_catalogue_recordings(tmp_path / "data" / "pedestrians")
    monkeypatch.setenv("TGRF_JAX_DATA", str(tmp_path / "data"))
    out = tmp_path / "zara.npz"
    argv = ["collect", "--recordings", "zara1", "zara2", "--chunk-steps", "20", "--out", str(out)]
    assert cli.main(argv) == 0
    assert "wrote" in capsys.readouterr().out
    dataset = data_lib.load_dataset(out)
    arrays = dataset["arrays"]
    assert dataset["config"]["crowd"] == data_lib.RECORDED and arrays["visible"].shape[1:] == (20, 3)
    # two files of 81 steps (20 s at dt 0.25) in envs of 20 steps: 4 each (the last step is too short for a
    # window and left out); everyone walks a straight line
    assert arrays["visible"].shape[0] == 8 and arrays["visible"].sum() == 2 * 80 * 3
    train, held_out = data_lib.split_index(arrays)
    assert len(train) and len(held_out)
    evaluate = train_lib.make_evaluator(data_lib.device_arrays(arrays))
    every = data_lib.window_index(arrays["visible"], arrays["seg"], range(arrays["visible"].shape[0]))
    metrics = evaluate(predictor.pretrained("orca"), every)
    assert metrics["cv_ade"] < 1e-4  # constant velocity is exact on straight walkers
    assert (
        cli.main(
            ["eval", "--dataset", str(out), "--pretrained", "orca", "--all-envs", "--out", str(tmp_path / "e.json")]
        )
        == 0
    )
    assert json.loads((tmp_path / "e.json").read_text())["cv_ade"] < 1e-4
