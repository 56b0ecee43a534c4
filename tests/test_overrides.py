"""``--set KEY=VALUE``: settings of the nested processing config changed from the command line."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from couch.capture.segmentation import SegmentationConfig
from couch.fitting import ProcessConfig
from couch.overrides import with_overrides
from couch.tools.bench import accuracy
from couch.tools.process import main as process_main


@dataclasses.dataclass(frozen=True)
class _Inner:
    scale: float = 1.0
    steps: int = 3
    name: str = "a"
    on: bool = True
    where: Path | None = None
    band: tuple[float, ...] = (0.1, 0.2)


@dataclasses.dataclass(frozen=True)
class _Outer:
    inner: _Inner = dataclasses.field(default_factory=_Inner)
    maybe: _Inner | None = None
    limit: int | None = 4


def test_each_field_type_is_parsed():
    given = _Outer()
    c = with_overrides(given, ["inner.scale=0.25", "inner.steps=7", "inner.name=b c",
                               "inner.on=no", "inner.where=/x/y", "inner.band=1,2,3",
                               "limit=none"])
    assert c.inner == _Inner(0.25, 7, "b c", False, Path("/x/y"), (1.0, 2.0, 3.0))
    assert c.limit is None and c.maybe is None
    assert given == _Outer()  # the input is untouched (frozen copies)


def test_a_group_left_to_its_default_is_filled_in():
    c = with_overrides(_Outer(), ["maybe.steps=9"])
    assert c.maybe == _Inner(steps=9)
    # the processing config: segmentation None means the capture stage's defaults
    p = with_overrides(ProcessConfig(), ["fit.segmentation.chair_distance=0.01",
                                         "fit.body.clothing_margin=0.005", "chair_frames=12"])
    assert p.fit.segmentation == dataclasses.replace(SegmentationConfig(), chair_distance=0.01)
    assert p.fit.body.clothing_margin == 0.005 and p.chair_frames == 12
    assert p.fit.shape == ProcessConfig().fit.shape and p.contacts == ProcessConfig().contacts


@pytest.mark.parametrize(("item", "says"), [
    ("inner.nope=1", "_Inner has no setting 'nope' (it has band, name, on, scale, steps, where)"),
    ("inner=1", "inner is a group of settings"),
    ("inner.steps=2.5", "--set inner.steps=2.5: invalid literal"),
    ("inner.on=maybe", "not a yes/no value"),
    ("limit.steps=1", "limit is not a group of settings"),
    ("inner.steps", "expected KEY=VALUE"),
])
def test_bad_items_name_the_key(item, says):
    with pytest.raises(ValueError) as err:
        with_overrides(_Outer(), [item])
    assert says in str(err.value)


def test_a_configs_own_checks_name_the_key():
    with pytest.raises(ValueError, match=r"--set contacts.enter_distance=0.03: ContactConfig: "
                                         r"leave thresholds must not be below"):
        with_overrides(ProcessConfig(), ["contacts.enter_distance=0.03"])  # leave is 0.025
    c = with_overrides(ProcessConfig(), ["contacts.leave_distance=0.04",
                                         "contacts.enter_distance=0.03"])  # in order: fine
    assert (c.contacts.enter_distance, c.contacts.leave_distance) == (0.03, 0.04)


def test_the_commands_refuse_a_bad_key_before_any_work(tmp_path, capsys):
    for main in (process_main, accuracy.main):
        args = [str(tmp_path)] if main is process_main else ["-o", str(tmp_path)]
        with pytest.raises(SystemExit) as exit_:
            main([*args, "--set", "fit.body.clothing=0.01"])
        assert exit_.value.code == 2
        assert "BodyFitConfig has no setting 'clothing'" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
