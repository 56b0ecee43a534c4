"""``couch-select``: the networks that synthesise best on validation chairs are kept, from
whichever candidate run holds them (machinery on the session's ci-trained run; a candidate is
made worse by scrambling its PoseNet's weights: its character never walks to the chair. The
``ci`` baseline itself barely reaches a chair in a few seconds, and a scrambled one can end
nearer, so the baselines are only checked to be kept by their rows)."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from couch.synthesis import Synthesizer
from couch.tools.select import main, select_networks


def _scramble(path) -> None:
    """Replace every weight of the checkpoint at ``path`` by noise of the same spread."""
    ck = torch.load(path, weights_only=True)
    gen = torch.Generator().manual_seed(3)
    ck["model"] = {k: (torch.randn(v.shape, generator=gen) * v.float().std().nan_to_num(1.0)
                       + v.float().mean()).to(v.dtype) if v.is_floating_point() and v.numel() > 1
                   else v for k, v in ck["model"].items()}
    torch.save(ck, path)


@pytest.fixture(scope="module")
def candidates(ci_run, tmp_path_factory):
    """Two runs: #0 the trained one, #1 the trained one with its PoseNet and its baseline
    scrambled (ControlNet the same in both)."""
    root = tmp_path_factory.mktemp("select")
    runs = []
    for i in range(2):
        run = root / f"run{i}"
        for net in ("pose", "control", "baseline", "contact"):
            shutil.copytree(ci_run.run_dir / net, run / net,
                            ignore=shutil.ignore_patterns("epochs", "checkpoint.pt"))
        if i:
            _scramble(run / "pose" / "best.pt")
            _scramble(run / "baseline" / "best.pt")
        runs.append(run)
    return runs


def test_select_keeps_the_networks_that_reach_their_contacts(candidates, tmp_path):
    out = tmp_path / "selected"
    sel = select_networks(candidates, out, chairs=1, trials=2, seconds=6, seed=7,
                          progress=False)
    rows = sel.rows
    assert set(rows) == {"couch #0 + #0", "couch #0 + #1", "couch #1 + #0", "couch #1 + #1",
                         "baseline #0", "baseline #1"}
    # the scrambled PoseNet misses by far, with either ControlNet, and the trained one is kept
    for c in (0, 1):
        assert rows[f"couch #1 + #{c}"]["ACE cm"] > rows["couch #0 + #0"]["ACE cm"] + 5
    assert sel.pose == candidates[0]
    # the two candidates' ControlNets are one network: the same trials, the same hands
    assert rows["couch #0 + #1"]["ACE cm"] == rows["couch #0 + #0"]["ACE cm"]
    assert sel.control == candidates[0] and sel.contact == candidates[0]  # first of a tie
    kept = min((0, 1), key=lambda b: rows[f"baseline #{b}"]["ACE cm"])
    assert sel.baseline == candidates[kept]
    for net, src in (("pose", sel.pose), ("control", sel.control),
                     ("baseline", sel.baseline), ("contact", sel.contact)):
        assert (out / net / "best.pt").read_bytes() == (src / net / "best.pt").read_bytes()
        assert (out / net / "stats.npz").is_file()
    Synthesizer(out, "couch")  # a run couch-eval and couch-synthesize read
    Synthesizer(out, "baseline")
    doc = json.loads((out / "selection.json").read_text())
    assert doc["chosen"] == {"couch": "couch #0 + #0", "baseline": f"baseline #{kept}"}
    assert doc["sources"]["baseline"] == str(candidates[kept])
    assert doc["rows"]["baseline #1"]["ACE cm"] == pytest.approx(rows["baseline #1"]["ACE cm"])
    assert "| couch #1 + #1 |" in (out / "selection.md").read_text()
    # a second selection into the same folder would mix two selections: refused
    with pytest.raises(ValueError, match="already holds pose, control, baseline, contact"):
        select_networks(candidates, out, chairs=1, trials=1, seconds=1, progress=False)


def test_couch_select_bad_input(candidates, tmp_path, capsys):
    assert main([str(tmp_path / "nowhere"), "-o", str(tmp_path / "o")]) == 2
    assert "nowhere: no such run folder" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main([str(empty), "-o", str(tmp_path / "o")]) == 2
    assert "no trained pose + control pair nor baseline" in capsys.readouterr().err
    assert main([str(candidates[0]), "-o", str(tmp_path / "o"), "--trials", "0"]) == 2
    assert not (tmp_path / "o").exists()
    (tmp_path / "file").write_text("")
    assert main([str(empty), "-o", str(tmp_path / "file")]) == 2
    assert "file: not a folder" in capsys.readouterr().err
