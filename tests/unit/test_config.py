"""Configuration: TOML -> frozen dataclasses; every value validated, unknown keys rejected by name."""

from __future__ import annotations

import tomllib
from dataclasses import FrozenInstanceError
from pathlib import Path

import pytest

from magcomp.adapters.config import Config, ConfigError, config_to_dict, load_config
from magcomp.errors import InputError

REPO = Path(__file__).parents[2]


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "c.toml"
    p.write_text(text)
    return p


def test_default_toml_mirrors_builtin_defaults_key_for_key() -> None:
    data = tomllib.loads((REPO / "config" / "default.toml").read_text())
    assert data == config_to_dict(Config())
    assert load_config(REPO / "config" / "default.toml") == Config()


def test_example_configs_load() -> None:
    paths = sorted((REPO / "config").rglob("*.toml"))
    assert len(paths) >= 4
    for p in paths:
        load_config(p)


def test_partial_file_overrides_only_its_keys(tmp_path: Path) -> None:
    cfg = load_config(_write(tmp_path, "[observer]\nk1 = 3\n[input]\ncompasses = [0, 2]\n"))
    assert cfg.observer.k1 == 3.0 and isinstance(cfg.observer.k1, float)
    assert cfg.input.compasses == (0, 2)
    assert cfg.observer.k2 == Config().observer.k2
    assert cfg.filter == Config().filter


def test_observer_section_defaults_and_bounds_are_the_core_parameters(tmp_path: Path) -> None:
    """One Config -> Params function: the [observer] defaults give ObserverParams' own defaults, and a
    value the core refuses (k1 = 0: Theorem 1 needs k1 > 0) is refused by the configuration too."""
    from magcomp.core.observer import ObserverParams
    from magcomp.service.estimators import observer_params

    assert observer_params(Config()) == ObserverParams()
    for key in ("k1", "k2"):
        with pytest.raises(ConfigError, match=key):
            load_config(_write(tmp_path, f"[observer]\n{key} = 0.0\n"))
        with pytest.raises(InputError):
            ObserverParams(**{"k1_1_s" if key == "k1" else "k2": 0.0})  # type: ignore[arg-type]


def test_config_is_frozen() -> None:
    with pytest.raises(FrozenInstanceError):
        Config().observer.k1 = 5.0  # type: ignore[misc]


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[observer]\nk3 = 1\n", "unknown key 'k3' in [observer]"),
        ("[obsrver]\nk1 = 1\n", "unknown section [obsrver]"),
        ("[observer]\nk1 = -1\n", "[observer] k1 must be > 0, got -1"),
        ("[observer]\nk1 = 'fast'\n", "[observer] k1 must be a number"),
        ("[observer]\nk1 = nan\n", "[observer] k1 must be finite"),
        ("[filter]\norder = 3\n", "[filter] order must be 1 or 2, got 3"),
        ("[filter]\norder = 2.0\n", "[filter] order must be an integer"),
        ("[input]\nattitude = 'magic'\n", "[input] attitude must be one of auto, mahony, autopilot"),
        ("[input]\nthrottle_source = 'servo:x'\n", "[input] throttle_source must be"),
        ("[input]\ncompasses = [0, 9]\n", "[input] compasses must hold compass indices"),
        ("[location]\nlat_deg = 91\n", "[location] lat_deg must be in [-90, 90]"),
        ("[calibration]\nmode = 'sometimes'\n", "[calibration] mode must be one of"),
        ("[observer]\ndt_min_s = 0.5\ndt_max_s = 0.2\n", "dt_min_s (0.5) must be below dt_max_s"),
        ("observer = 3\n", "[observer] must be a table"),
        ("[observer\n", "not valid TOML"),
    ],
)
def test_bad_values_give_one_line_message_naming_the_key(tmp_path: Path, text: str, needle: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(_write(tmp_path, text))
    msg = str(info.value)
    assert needle in msg
    assert "\n" not in msg


def test_accepted_throttle_sources(tmp_path: Path) -> None:
    for src in ("auto", "servo:3", "rc:3", "motors", "vfr_hud", "ctun", "none"):
        cfg = load_config(_write(tmp_path, f"[input]\nthrottle_source = '{src}'\n"))
        assert cfg.input.throttle_source == src


def test_missing_file_and_directory_are_input_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_config(tmp_path / "absent.toml")
    with pytest.raises(ConfigError, match="is a directory"):
        load_config(tmp_path)
