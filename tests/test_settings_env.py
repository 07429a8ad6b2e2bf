"""Settings precedence: the CLI's arguments, then DRILLNAV_* environment variables, then the config file, then defaults."""

import pytest

from drillnav.service.settings import SettingsError, load_settings

from conftest import free_port

TOKEN = "file-token-of-16-chars"


def test_environment_overrides_the_file_key_by_key(tmp_path, monkeypatch):
    file_port, env_port = free_port(), free_port()  # values only: nothing binds them here
    cfg = tmp_path / "drillnav.toml"
    cfg.write_text(f'[api]\nport = {file_port}\ntoken = "{TOKEN}"\n[camera]\nfps = 25\n[twin_scene]\nseed = 4\n')
    assert load_settings(cfg).api.port == file_port

    monkeypatch.setenv("DRILLNAV_API__PORT", str(env_port))
    monkeypatch.setenv("DRILLNAV_TWIN_SCENE__SEED", "9")
    s = load_settings(cfg)
    assert s.api.port == env_port and s.twin_scene.seed == 9  # the environment wins
    assert s.api.token == TOKEN and s.camera.fps == 25.0  # what it does not name still comes from the file, section by section


def test_cli_arguments_override_the_environment(tmp_path, monkeypatch):
    cfg = tmp_path / "drillnav.toml"
    cfg.write_text("twin = false\n")
    monkeypatch.setenv("DRILLNAV_TWIN", "false")
    assert load_settings(cfg).twin is False
    assert load_settings(cfg, twin=True).twin is True  # `drillnav serve --twin`


def test_a_bad_environment_value_is_refused_naming_the_field(tmp_path, monkeypatch):
    cfg = tmp_path / "drillnav.toml"
    cfg.write_text("[camera]\nfps = 30\n")
    monkeypatch.setenv("DRILLNAV_CAMERA__FPS", "-5")
    with pytest.raises(SettingsError, match="camera.fps"):
        load_settings(cfg)


def test_an_unknown_top_level_file_key_is_still_refused(tmp_path):
    cfg = tmp_path / "drillnav.toml"
    cfg.write_text("colour = 1\n")
    with pytest.raises(SettingsError, match="colour"):  # a top-level key: the file is no longer constructor arguments
        load_settings(cfg)
