"""Pretrained policies: export from a run, play with tgrf-eval / tgrf-render --pretrained, clear errors."""

import json
import pathlib
import shutil

import pytest

from tgrf_jax import pretrained
from tgrf_jax.cli import eval_main, render_main
from tgrf_jax.config import ConfigError, TrainConfig, config_fields
from tgrf_jax.train.run_dir import train_run

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("pretrained")
    train_run(TrainConfig.from_yaml(TINY, ["run.eval_episodes=0"]), root / "run", log=lambda m: None)
    dest = pretrained.export(root / "run", root / "policy", meta={"note": "tiny"})
    return root / "run", dest


def test_export_writes_config_params_and_meta(exported):
    run_dir, dest = exported
    meta = json.loads((dest / "meta.json").read_text())
    assert meta["note"] == "tiny" and meta["update"] == 12 and meta["source"] == str(run_dir)
    manifest = json.loads((dest / "manifest.json").read_text())
    assert sorted(manifest["sha256"]) == ["config.yaml", "meta.json", "params.npz"]
    assert sorted(p.name for p in dest.parent.iterdir()) == ["policy", "run"]  # no temporary directory left
    config, params, _ = pretrained.load(str(dest))
    assert config == TrainConfig.from_yaml(run_dir / "config.yaml") and "params" in params


def test_eval_of_a_pretrained_policy_equals_eval_of_its_run(exported, tmp_path):
    run_dir, dest = exported
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    # 8 episodes: the evaluation program of the other tiny runs (tests/test_train_cli.py), compiled once per session
    assert eval_main(["--pretrained", str(dest), "--episodes", "8", "--out", str(a)]) == 0
    assert eval_main([str(run_dir), "--episodes", "8", "--out", str(b)]) == 0
    assert json.loads(a.read_text())["results"] == json.loads(b.read_text())["results"]


def test_render_a_pretrained_policy(exported, tmp_path):
    _, dest = exported
    out = tmp_path / "render"
    assert render_main(["--pretrained", str(dest), "--out", str(out), "--no-frames", "--no-mp4"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [e["policy"] for e in summary["episodes"]] == ["learned"] and summary["episodes"][0]["gif"]


def test_bad_pretrained_policies_are_named(exported, tmp_path, capsys):
    run_dir, dest = exported
    assert eval_main(["--pretrained", "nosuch"]) == 2
    assert "no pretrained policy 'nosuch'" in capsys.readouterr().err
    assert eval_main([str(run_dir), "--pretrained", str(dest)]) == 2
    assert "give no RUN_DIR|CONFIG" in capsys.readouterr().err
    broken = tmp_path / "broken"
    shutil.copytree(dest, broken)
    (broken / "params.npz").unlink()
    with pytest.raises(ConfigError, match="params.npz missing"):
        pretrained.load(str(broken))
    shutil.copy(dest / "params.npz", broken / "params.npz")
    (broken / "config.yaml").write_text((dest / "config.yaml").read_text().replace("name: mlp", "name: hh_attn"))
    with pytest.raises(ConfigError, match="config.yaml' does not match manifest.json"):
        pretrained.load(str(broken))
    pretrained.write_manifest(broken)  # as a hand-edited directory would: the checks behind the manifest hold
    with pytest.raises(ConfigError, match="does not fit the hh_attn/small network"):
        pretrained.load(str(broken))
    (broken / "config.yaml").write_text((dest / "config.yaml").read_text())
    (broken / "params.npz").write_bytes(b"not a zip file")
    pretrained.write_manifest(broken)
    with pytest.raises(ConfigError, match=r"params.npz': cannot read the parameters \(ValueError: "):
        pretrained.load(str(broken))
    (broken / "params.npz").write_bytes((dest / "params.npz").read_bytes()[:-100])  # truncated
    (broken / "meta.json").write_text("{")
    pretrained.write_manifest(broken)
    with pytest.raises(ConfigError, match=r"params.npz': cannot read the parameters") as caught:
        pretrained.load(str(broken))
    assert "\n" not in str(caught.value)
    shutil.copy(dest / "params.npz", broken / "params.npz")
    pretrained.write_manifest(broken)
    with pytest.raises(ConfigError, match=r"meta.json': cannot read the policy's metadata"):
        pretrained.load(str(broken))


def test_export_removes_leftovers_of_a_killed_export(exported):
    from tgrf_jax.pretrained.directory import PARTIAL_SUFFIX

    run_dir, dest = exported
    stale = dest.parent / f".policy.abc{PARTIAL_SUFFIX}"  # what a writer killed mid-way leaves (its lock released)
    stale.mkdir()
    (stale / "params.npz").write_bytes(b"half")
    pretrained.export(run_dir, dest, meta={"note": "tiny"})
    assert not stale.exists() and sorted(p.name for p in dest.parent.iterdir()) == ["policy", "run"]


def test_shipped_manifests_are_package_data():
    pyproject = (ROOT / "pyproject.toml").read_text()
    line = next(x for x in pyproject.splitlines() if x.startswith('"tgrf_jax.pretrained" ='))
    assert all(f'"*/{f}"' in line for f in (*pretrained.FILES, pretrained.MANIFEST_FILE)), line


@pytest.mark.parametrize("name", pretrained.available())
def test_shipped_policies_load_with_their_config(name):
    assert (pretrained.ROOT / name / pretrained.MANIFEST_FILE).is_file()
    # checks the files against the manifest, every parameter's name, shape, dtype and finiteness
    config, params, meta = pretrained.load(name)
    assert meta["row"] in name
    # the values its experiment compared or searched (reward.scheme, reward.h_wall, a tune's reward.h_disc and
    # reward.sigma_disc, ...) are the ones the policy was trained with
    compared = [key for key in meta if key in config_fields()]
    assert compared, sorted(meta)
    for key in compared:
        section, field = key.split(".")
        trained = getattr(getattr(config, section), field)
        assert str(trained) == str(meta[key]) or (isinstance(trained, float) and trained == float(meta[key])), (
            key,
            trained,
        )
    assert 0.0 < meta["test"]["success_rate"] <= 1.0
