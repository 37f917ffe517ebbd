"""The physics settings are declared once (sim/physics/settings.py): the dataclass, the campaign
file's [[physics]] keys, the command-line options and the docs agree with the declaration, and a
value out of range is refused naming the setting, its unit and the range, from a campaign file
and from the command line."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from sim.campaign.config import PhysicsConfig, parse_campaign
from sim.core.cliargs import OptionError, Range, add_options, from_namespace
from sim.core.errors import InputError
from sim.physics import PhysicsError
from sim.physics.settings import FORMER_NAMES, SETTINGS, PhysicsSettings, campaign_settings, campaign_table_rows
from tests.conftest import REPO

#: The defaults as they were before the declaration was unified (results must not change).
DEFAULTS = {"level": "poly", "kvp": 120.0, "anode_angle_deg": 12.0, "filters": (("Al", 2.5),), "bins": 30,
            "mas": 2.5, "detector_mm": 0.6, "detector_mode": "integrating", "noise": True, "seed": 0, "blur_mm": 0.3,
            "electronic_noise": 0.0, "scatter_photons": 1_000_000, "scatter_voxel_mm": 6.0, "grid_ratio": 0.0}

#: The ranges as the physics accepts them (spekpy's tube model, the detector, the Monte Carlo).
RANGES = {"kvp": "in [20, 150]", "anode_angle_deg": "in [1, 45]", "bins": "in [1, 1000]", "mas": "> 0",
          "detector_mm": "> 0", "seed": ">= 0", "blur_mm": ">= 0", "electronic_noise": ">= 0",
          "scatter_photons": ">= 1000", "scatter_voxel_mm": "in (0, 100]", "grid_ratio": "in [0, 50]"}

NUMERIC = [s for s in SETTINGS.values() if s.kind in ("int", "float")]


def outside(s) -> list:
    """Values just outside the setting's range (each bound that exists)."""
    step = 1 if s.kind == "int" else 0.5
    bad = []
    if s.low is not None:
        bad.append(s.low if s.low_open else s.low - step)
    if s.high is not None:
        bad.append(s.high if s.high_open else s.high + step)
    return bad


def assert_names_setting(message: str, s, spelling: str) -> None:
    """The message names the setting (as spelled where it came from), its unit and range."""
    assert spelling in message, message
    assert s.range_text() in message, message
    if s.unit:
        assert s.unit in message, message


def test_the_declaration_is_the_dataclass_with_the_old_defaults_and_ranges():
    fields = dataclasses.fields(PhysicsSettings)
    assert [f.name for f in fields] == list(SETTINGS)
    assert {f.name: f.default for f in fields} == {n: s.default for n, s in SETTINGS.items()} == DEFAULTS
    assert dataclasses.asdict(PhysicsSettings()) == DEFAULTS
    assert {s.name: s.range_text() for s in NUMERIC} == RANGES
    assert SETTINGS["detector_mode"].choices == ("integrating", "counting")
    assert {s.name for s in SETTINGS.values() if s.levels == ("full",)} == {"scatter_photons", "scatter_voxel_mm",
                                                                            "grid_ratio"}
    # one spelling: no former name is still a setting
    assert not set(FORMER_NAMES) & set(SETTINGS) and set(FORMER_NAMES.values()) <= set(SETTINGS)


def test_settings_normalise_their_values():
    p = PhysicsSettings(kvp=100, filters=["Al:2.5", ("Cu", 0)], mas=5)
    assert p.kvp == 100.0 and isinstance(p.kvp, float) and isinstance(p.mas, float)
    assert p.filters == (("Al", 2.5), ("Cu", 0.0))


def test_the_campaign_entry_has_one_field_per_setting_with_its_default():
    fields = {f.name: f.default for f in dataclasses.fields(PhysicsConfig)}
    for s in campaign_settings():
        assert fields[s.name] == s.default, s.name
    assert {s.name for s in campaign_settings()} == set(SETTINGS) - {"level", "seed"}
    assert "n_bins" not in fields and "bins" in fields


def _campaign(tmp_path, entry: dict) -> dict:
    return {"campaign": {"name": "t", "images_per_ct": 1}, "physics": [entry], "cts": [{"path": "phantom:0"}]}


def test_every_campaign_key_reaches_the_settings_and_back(tmp_path):
    """A full entry that sets every key to a non-default value: the parsed entry and its
    PhysicsSettings hold those values, and to_dict reads back to an equal entry (the manifest)."""
    values = {"kvp": 90.0, "anode_angle_deg": 10.0, "filters": ["Al:2", "Cu:0.1"], "bins": 20, "mas": 1.5,
              "detector_mm": 0.5, "detector_mode": "counting", "noise": False, "blur_mm": 0.2,
              "electronic_noise": 3.0, "scatter_photons": 5000, "scatter_voxel_mm": 8.0, "grid_ratio": 10.0}
    assert set(values) == {s.name for s in campaign_settings()}
    cfg = parse_campaign(_campaign(tmp_path, {"name": "f", "level": "full", **values}), base_dir=tmp_path)
    entry = cfg.physics[0]
    settings = entry.settings()
    for name, v in values.items():
        expect = (("Al", 2.0), ("Cu", 0.1)) if name == "filters" else v
        assert getattr(entry, name) == getattr(settings, name) == expect, name
    assert entry.to_dict() == {"name": "f", "level": "full", "ray_model": "siddon", "step_fraction": 0.5,
                               "mu_water_per_mm": entry.mu_water_per_mm, **values}
    again = parse_campaign(cfg.to_dict(), base_dir=tmp_path)
    assert again == cfg and again.config_hash() == cfg.config_hash()
    # the default of every key written out or left out: the same entry and hash
    plain = parse_campaign(_campaign(tmp_path, {"name": "f", "level": "full"}), base_dir=tmp_path)
    spelled = parse_campaign(_campaign(tmp_path, {"name": "f", "level": "full", **{
        s.name: s.text(s.default) for s in campaign_settings()}}), base_dir=tmp_path)
    assert plain == spelled and plain.config_hash() == spelled.config_hash()
    assert plain.physics[0].settings() == PhysicsSettings(level="full")


@pytest.mark.parametrize("s", [s for s in NUMERIC if s.campaign], ids=lambda s: s.name)
def test_a_campaign_value_out_of_range_names_key_unit_and_range(tmp_path, s):
    for bad in outside(s):
        entry = {"name": "p", "level": "full", s.name: bad}
        with pytest.raises(InputError) as info:
            parse_campaign(_campaign(tmp_path, entry), base_dir=tmp_path)
        assert_names_setting(str(info.value), s, f"physics[0].{s.name}")
        with pytest.raises(PhysicsError) as info:
            PhysicsSettings(level="full", **{s.name: bad})
        assert_names_setting(str(info.value), s, s.name)


def test_campaign_choices_filters_levels_and_former_spellings_are_named(tmp_path):
    def error(entry):
        with pytest.raises(InputError) as info:
            parse_campaign(_campaign(tmp_path, {"name": "p", **entry}), base_dir=tmp_path)
        return str(info.value)

    msg = error({"level": "poly", "detector_mode": "hybrid"})
    assert "physics[0].detector_mode" in msg and "integrating, counting" in msg and "'hybrid'" in msg
    msg = error({"level": "poly", "filters": ["Xx:1"]})
    assert "physics[0].filters" in msg and "SYMBOL:MM" in msg and "mm >= 0" in msg
    assert "physics[0].filters" in error({"level": "poly", "filters": "Al:2.5"})
    assert "physics[0].noise" in error({"level": "poly", "noise": 1})
    msg = error({"level": "poly", "scatter_voxel_mm": 4.0})
    assert "physics[0].scatter_voxel_mm" in msg and 'only for level = "full"' in msg
    msg = error({"bins": 20})
    assert "physics[0].bins" in msg and 'only for level = "poly" or "full"' in msg
    for old, new in FORMER_NAMES.items():
        msg = error({"level": "full", old: SETTINGS[new].text(SETTINGS[new].default)})
        assert f"physics[0].{old}" in msg and repr(new) in msg and SETTINGS[new].flag in msg, msg


def _parser(cls) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(argument_default=argparse.SUPPRESS)
    add_options(parser, cls)
    return parser


def _commands():
    from register.commands import REGISTER_SCATTER_PHOTONS, RegisterCommand
    from sim.cli import RenderCommand

    return {RenderCommand: {}, RegisterCommand: {"scatter_photons": REGISTER_SCATTER_PHOTONS}}


def test_the_command_line_options_are_the_settings():
    """Field name = setting name = option (``_`` -> ``-``); default, unit, range and choices from the
    declaration; every option of render is a setting (or --label-material), register has the
    spectrum and scatter ones (its moving images have no noise)."""
    for cls, own_defaults in _commands().items():
        fields = {f.name: f for f in dataclasses.fields(cls)}
        parser = _parser(cls)
        physics = {n for n in fields if n in SETTINGS and SETTINGS[n].cli}
        for name in physics:
            s, f = SETTINGS[name], fields[name]
            assert s.flag in parser._option_string_actions, (cls.__name__, s.flag)
            default = own_defaults.get(name, s.default)
            assert f.default == (tuple(s.text(default)) if s.kind == "filters" else default), name
            meta = f.metadata
            assert meta["unit"] == s.unit and meta["help"].startswith(s.help), name
            if s.kind == "choice":
                assert tuple(meta["choices"]) == s.choices
            if s.kind in ("int", "float"):
                assert meta["bounds"] == Range(s.low, s.high, s.low_open), name
                assert str(meta["bounds"]) == s.range_text()
        for old in FORMER_NAMES:
            assert old not in fields and "--" + old.replace("_", "-") not in parser._option_string_actions
    render = {f.name for f in dataclasses.fields(next(iter(_commands())))}
    assert {s.name for s in SETTINGS.values() if s.cli} <= render


@pytest.mark.parametrize("s", [s for s in NUMERIC if s.cli], ids=lambda s: s.name)
def test_a_command_line_value_out_of_range_names_option_unit_and_range(s):
    from sim.cli import RenderCommand
    from sim.physics.options import check_level_options

    for bad in outside(s):
        text = str(int(bad)) if s.kind == "int" else repr(float(bad))
        ns = _parser(RenderCommand).parse_args(["--ct", "phantom", "--physics", "full", s.flag, text])
        with pytest.raises(OptionError) as info:
            from_namespace(RenderCommand, ns)
        assert_names_setting(str(info.value), s, s.flag)
        # a command built in Python (no argparse) is refused the same way
        with pytest.raises(PhysicsError) as info:
            check_level_options(RenderCommand(ct="phantom", physics="full", **{s.name: bad}))
        assert_names_setting(str(info.value), s, s.flag)


def test_the_command_line_refuses_bad_filters_choices_and_non_finite_values(capsys):
    from register.cli import main

    assert main(["render", "--ct", "phantom", "--physics", "poly", "--filters", "Xx:1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--filters" in err and "SYMBOL:MM" in err and "mm >= 0" in err, err
    assert main(["render", "--ct", "phantom", "--physics", "poly", "--kvp", "300"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--kvp" in err and "[20, 150] kV" in err, err
    assert main(["render", "--ct", "phantom", "--physics", "poly", "--mas", "nan"]) == 2
    assert "--mas" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["render", "--ct", "phantom", "--physics", "poly", "--detector-mode", "hybrid"])
    err = capsys.readouterr().err
    assert "--detector-mode" in err and "integrating" in err


def test_the_physics_components_take_the_ranges_of_the_settings():
    """tube_spectrum, Detector and ScatterSettings refuse what the settings refuse (their shared
    parameters' ranges are the settings')."""
    from sim.physics.poly import Detector
    from sim.physics.scatter import ScatterSettings
    from sim.physics.spectrum import DEFAULT_BINS, tube_spectrum

    assert DEFAULT_BINS == SETTINGS["bins"].default
    for kwargs in (dict(kvp=19.5), dict(anode_angle_deg=46.0), dict(bins=1001)):
        with pytest.raises(PhysicsError):
            tube_spectrum(**kwargs)
    for kwargs in (dict(thickness_mm=0.0), dict(blur_mm=-0.1), dict(electronic_noise=-1.0), dict(mode="film")):
        with pytest.raises(PhysicsError):
            Detector(**kwargs)
    for kwargs in (dict(photons=999), dict(voxel_mm=100.5), dict(voxel_mm=0.0), dict(grid_ratio=50.5)):
        with pytest.raises(PhysicsError):
            ScatterSettings(**kwargs)
    assert ScatterSettings(photons=1000, voxel_mm=100.0, grid_ratio=50.0).voxel_mm == 100.0
    d = Detector()
    assert (d.thickness_mm, d.mode, d.electronic_noise) == (0.6, "integrating", 0.0)


def test_the_campaign_docs_list_every_setting_as_declared():
    text = (REPO / "docs" / "campaigns.md").read_text()
    for row in campaign_table_rows():
        assert row in text, row
