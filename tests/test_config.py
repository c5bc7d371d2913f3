"""The pipeline's configuration: defaults, the capture's odsplat.toml, --set, and one-line refusals."""
from __future__ import annotations

import pytest

from odsplat.app.config import Config, load_config, parse_set
from odsplat.spine.errors import InputError


def test_layers_override_in_order_and_automatic_settings_stay_automatic(tmp_path):
    path = tmp_path / "odsplat.toml"
    path.write_text("[magnify]\nalpha = 30\nband_hz = [20, 400]\n[reconstruct.fit]\niters_t0 = 800\n")
    c = load_config(path=path, sets=("magnify.alpha=50", "reconstruct.motion=timestep"))
    assert c.magnify.alpha == 50.0 and c.magnify.band_hz == (20.0, 400.0)
    assert c.reconstruct.fit.iters_t0 == 800 and c.reconstruct.fit.iters_per_step == 150   # the rest default
    # The file says nothing of the frames: the per-timestep model's default source follows its motion.
    assert c.reconstruct.source == "magnified/phase"
    assert load_config(path=path).reconstruct.source == "sync"
    assert c.sources == ("defaults", str(path), "--set magnify.alpha=50", "--set reconstruct.motion=timestep")
    assert Config.defaults().to_dict() == load_config().to_dict()


@pytest.mark.parametrize("item, value", [
    ("magnify.alpha=30", {"magnify": {"alpha": 30}}),
    ("magnify.band_hz=[20, 400]", {"magnify": {"band_hz": [20, 400]}}),
    ("reconstruct.motion=timestep", {"reconstruct": {"motion": "timestep"}}),
    ("reconstruct.fit.iters_t0=10", {"reconstruct": {"fit": {"iters_t0": 10}}}),
    ("sync.plot=false", {"sync": {"plot": False}}),
])
def test_parse_set(item, value):
    assert parse_set(item) == value


@pytest.mark.parametrize("sets, where, message", [
    (("magnify",), "--set", "expected STAGE.FIELD=VALUE"),
    (("render.width=3",), "--set render.width=3", "unknown stage"),
    (("magnify.alhpa=3",), "--set magnify.alhpa=3: magnify", "unknown field"),
    (("magnify.alpha=fast",), "--set magnify.alpha=fast: magnify.alpha", "expected a number"),
    (("magnify.alpha=-2",), "MagnifySettings.alpha", "expected a finite number > 0 and <= 10000"),
    (("reconstruct.source=frames",), "source", "expected 'sync' or 'magnified/METHOD'"),
])
def test_bad_settings_are_named(sets, where, message):
    with pytest.raises(InputError, match=message) as err:
        load_config(sets=sets)
    assert err.value.source == where


def test_the_printed_configuration_reads_back(tmp_path):
    c = load_config(sets=("analyze.fmax_hz=900", "magnify.band_hz=[20, 400]"))
    text = c.to_toml()
    assert "# automatic (unset):" in text and "analyze.fmin_hz" in text
    path = tmp_path / "odsplat.toml"
    path.write_text(text)
    assert load_config(path=path).to_dict() == c.to_dict()


def test_magnify_does_one_view_unless_the_reconstruction_reads_magnified_frames():
    """Issue 44: magnified frames are for watching, one view by default; a reconstruction from them (source
    magnified/METHOD) needs every view's, so `odsplat run` magnifies them all then, unless views are named."""
    from odsplat.app.config import Config
    c = Config.defaults()
    assert c.magnify.views == () and not c.magnify.every_view
    t = Config(table={"reconstruct": {"motion": "timestep"}})
    assert t.reconstruct.source == "magnified/phase" and t.magnify.every_view
    named = Config(table={"reconstruct": {"source": "magnified/phase"}, "magnify": {"views": [3]}})
    assert named.magnify.views == (3,) and not named.magnify.every_view
