"""The notebooks: committed without outputs, and each runs top to bottom (nbclient, a python3 kernel of the current
interpreter). Their run time (about a minute each on 2 idle CPU cores, budget 3 minutes) is printed, not asserted:
speed belongs to benchmarks, and a busy machine must not fail a correct notebook."""

import csv
import os
import pathlib
import queue
import sys
import time

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = ROOT / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
CELL_TIMEOUT_S = 180  # a hang guard per cell (nbclient), not a speed check


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_committed_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    assert nb.metadata.kernelspec.name == "python3"
    assert "widgets" not in nb.metadata  # no saved widget state
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert cell.outputs == [], f"{path.name}: cell {i} carries outputs; strip them before committing"
            assert cell.execution_count is None, f"{path.name}: cell {i} has an execution count"
            assert "execution" not in cell.metadata, f"{path.name}: cell {i} has execution timing metadata"


def _outputs(nb, kind):
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        for out in cell.outputs:
            if kind == "stream" and out.output_type == "stream":
                yield out.text
            elif kind != "stream" and kind in out.get("data", {}):
                yield out.data[kind]


def _poll_in_short_steps(channel, step_s=0.5):
    """Make a kernel client channel wait for its next message in short polls instead of one long one.

    The asyncio zmq poll behind jupyter_client's ``get_msg`` can miss the wake-up for a message that is already
    queued (nbclient#312): seen here on the cell that opens ipywidgets comms, which then sat until the cell
    timeout (180 s) with its reply waiting in the socket. Each short poll checks the socket again on return, so a
    missed wake-up costs at most one step, and the overall timeout the caller asked for is kept.
    """
    wait = channel.get_msg

    async def get_msg(timeout=None):
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = step_s if deadline is None else max(0.0, min(step_s, deadline - time.monotonic()))
            try:
                return await wait(timeout=left)
            except queue.Empty:
                if deadline is not None and time.monotonic() >= deadline:
                    raise

    channel.get_msg = get_msg


def _execute(path, tmp_path):
    nb = nbformat.read(path, as_version=4)
    env = dict(os.environ)
    # The kernel imports tgrf_jax from this checkout even where it is not pip-installed; the default (CI) budget.
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    for var in ("TGRF_NB_STEPS", "TGRF_NB_EPISODES"):
        env.pop(var, None)
    env["TGRF_NB_RUN_DIR"] = str(tmp_path)

    def short_polls(**_):
        _poll_in_short_steps(client.kc.shell_channel)
        _poll_in_short_steps(client.kc.iopub_channel)

    client = NotebookClient(
        nb,
        timeout=CELL_TIMEOUT_S,
        kernel_name="python3",
        on_notebook_start=short_polls,
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    start = time.perf_counter()
    client.execute(env=env)
    elapsed = time.perf_counter() - start
    print(f"{path.name}: executed in {elapsed:.1f} s with {sys.executable}")
    return nb


def test_reward_shapes_runs(tmp_path):
    nb = _execute(NOTEBOOK_DIR / "reward_shapes.ipynb", tmp_path)
    text = "".join(_outputs(nb, "stream"))
    assert "max |jax.grad - finite diff|" in text and "R_disc recomputed" in text
    assert "dR/dh" in text and "dR/dsigma" in text
    # Static figures always render: distance curves, surfaces, slider default, frame, terms, comparison, gradients.
    assert len(list(_outputs(nb, "image/png"))) >= 7


@pytest.mark.slow  # trains a policy and runs a tune: a training run, kept out of CI
def test_train_and_evaluate_runs(tmp_path):
    nb = _execute(NOTEBOOK_DIR / "train_and_evaluate.ipynb", tmp_path)
    rows = list(csv.DictReader(open(tmp_path / "run" / "metrics.csv")))
    assert [int(r["update"]) for r in rows] == [5, 10, 15]  # 7,680 steps of 16 envs x 32: the whole run trained
    table = "".join(_outputs(nb, "text/markdown"))
    assert all(f"| {name} |" in table for name in ("learned", "straight", "orca"))
    html = "".join(_outputs(nb, "text/html"))
    assert "<script" in html and "data:image/png;base64" in html  # the inline animation
    # The room built by hand: its layout and LiDAR scans were recorded, and its frame drawn.
    text = "".join(_outputs(nb, "stream"))
    assert "3 obstacles, LiDAR scans of shape (" in text and ", 72)" in text
    (room,) = [c for c in nb.cells if c.cell_type == "code" and "show_rays=True" in c.source]
    assert any("image/png" in out.get("data", {}) for out in room.outputs)
    assert (tmp_path / "run" / "config.yaml").is_file()
    # The tune: two exploit steps of 4 members, its report and figures shown inline.
    assert len((tmp_path / "tune" / "lineage.csv").read_text().splitlines()) == 1 + 2 * 4
    assert "Best member m" in table
    (tune,) = [c for c in nb.cells if c.cell_type == "code" and "run_tune(" in c.source]
    assert sum("image/png" in out.get("data", {}) for out in tune.outputs) == 2
