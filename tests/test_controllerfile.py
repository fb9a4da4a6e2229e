"""Controller files: what `vcyto calibrate` writes, `vcyto stream --controller` reads back (units included)."""

import dataclasses
import json
import math
import subprocess
import sys

import pytest

from controller.sorter import ControllerSettings
from sim.model.scenario import ScenarioError
from vcyto.controllerfile import controller_toml, load_controller


def test_a_written_controller_file_reads_back_as_the_same_settings(tmp_path):
    settings = ControllerSettings(delay=0.61e-3, reference_velocity=0.105, lead=0.25e-3, pulse=0.35e-3,
                                  mode="yield", envelope=(-0.2e-3, 0.19e-3), timing_error=0.02e-3)
    path = tmp_path / "controller.toml"
    path.write_text(controller_toml(settings, {"model": "rom", "cells": 12}))
    loaded = load_controller(path)
    for field in dataclasses.fields(ControllerSettings):
        expected, got = getattr(settings, field.name), getattr(loaded, field.name)
        if isinstance(expected, float):
            assert math.isclose(got, expected, rel_tol=1e-6), field.name
        elif isinstance(expected, tuple):
            assert all(math.isclose(g, e, rel_tol=1e-6) for g, e in zip(got, expected)), field.name
        else:
            assert got == expected, field.name


def test_a_controller_time_with_a_length_unit_is_refused_naming_the_field(tmp_path):
    path = tmp_path / "controller.toml"
    path.write_text(controller_toml(ControllerSettings(), {}).replace('lead = "0.3 ms"', 'lead = "0.3 um"'))
    with pytest.raises(ScenarioError, match="lead"):
        load_controller(path)


def test_stream_runs_with_the_file_calibrate_wrote(tmp_path):
    path = tmp_path / "controller.toml"
    path.write_text(controller_toml(ControllerSettings(lead=0.28e-3), {"model": "rom"}))
    done = subprocess.run([sys.executable, "-m", "vcyto", "stream", "--model", "rom", "--count", "20", "--mix",
                           "RBC:0.8,melanoma:0.2", "--controller", str(path), "--no-viewer", "--output", "",
                           "--json", "--quiet"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert math.isclose(json.loads(done.stdout)["controller"]["lead_ms"], 0.28, rel_tol=1e-9)


def test_an_interrupted_calibration_reports_what_it_measured_and_saves_nothing(monkeypatch, tmp_path, capsys):
    """Ctrl-C in the pulse search: the delay and the pulses tried so far are printed, marked PARTIAL; exit 130;
    no controller file (it needs every measurement)."""
    from vcyto.cli import main
    from vcyto.studies import calibrate

    def fake_search(plant, scenario, detector, delay, grid, required, progress=None, tried=None):
        tried.append(calibrate.PulseBand(0.02e-3, None))
        tried.append(calibrate.PulseBand(0.04e-3, (0.0, 10e-6)))
        raise KeyboardInterrupt

    monkeypatch.setattr(calibrate, "make_calibration_plant", lambda scenario, model: type(
        "Plant", (), {"control_period": 10e-6, "reset": lambda self, *a, **k: None})())
    monkeypatch.setattr(calibrate, "measure_delay", lambda plant, scenario, detector: calibrate.Delay(
        {"I": 150e-6, "II": 151e-6}, {"I": 2e-6, "II": 3e-6}, {}))
    monkeypatch.setattr(calibrate, "shortest_pulse", fake_search)
    assert main(["calibrate", "--model", "rom", "--quiet", "--output", str(tmp_path)]) == 130
    report = capsys.readouterr().out.splitlines()
    assert report[0] == "detector to SAW window: class I 150.00 um, class II 151.00 um; timing error class I 2.0 us, " \
                        "class II 3.0 us"
    assert report[1:3] == ["pulse 0.020 ms: good leads none", "pulse 0.040 ms: good leads " +
                           calibrate._band_text((0.0, 10e-6))]
    assert report[-1].startswith("PARTIAL: interrupted after 0 calibration cells; nothing saved")
    assert list(tmp_path.iterdir()) == []
