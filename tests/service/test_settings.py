"""Settings: the fusion configuration an operator sets through the environment."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from service.settings import Settings, fusion_config, get_settings


def test_fusion_overrides_from_the_environment_apply_to_the_preset(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FLEETMAP_FUSION_SET", "realign_share=0.5; realign_iterations_fraction=0.5;thin_classes=pole,fence")
    config = fusion_config(Settings())
    assert (config.realign_share, config.realign_iterations_fraction) == (0.5, 0.5)
    assert config.thin_classes == ("pole", "fence")
    assert config.iterations == fusion_config(Settings(fusion_set="")).iterations  # the rest: the preset's
    tiny = fusion_config(Settings(fusion_preset="tiny", fusion_set="c_th=0.6"))
    assert tiny.c_th == 0.6 and tiny.iterations == 25


@pytest.mark.parametrize("value, says", [("nokey=1", "'nokey=1': expected KEY=VALUE"),
                                         ("realign_share=x", "'x' is not a valid float"),
                                         ("realign_share=0", "realign_share must be > 0"),
                                         ("refusion_carried_fraction=1.5",
                                          "refusion_carried_fraction must be in [0, 1], got 1.5")])
def test_a_bad_fusion_override_stops_the_process_at_start_up_with_one_line(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], value: str, says: str) -> None:
    from service.cli import main

    with pytest.raises(ValidationError):
        Settings(fusion_set=value)
    monkeypatch.setenv("FLEETMAP_FUSION_SET", value)
    get_settings.cache_clear()
    try:
        assert main(["serve"]) == 2
    finally:
        get_settings.cache_clear()
    err = capsys.readouterr().err.strip()
    assert err.startswith("fleetmap: error: FLEETMAP_FUSION_PRESET / FLEETMAP_FUSION_SET: ") and says in err, err
    assert "\n" not in err
