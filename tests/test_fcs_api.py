"""FCS a cytometrist can gate (FlowKit applies the exported Gating-ML gate) and the Python API."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim.model.arrivals import Arrivals
from sim.model.scenario import Scenario
from vcyto import __version__
from vcyto.recording.fcs import CHANNELS, write_fcs
from vcyto.recording.gatingml import GATE_IDS, write_gatingml
from vcyto.stream import StreamSettings, run_stream

USAGE = Path(__file__).resolve().parent.parent / "docs" / "usage.md"


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A streamline stream with noisy fluorescence (misclassifications) exported as FCS and Gating-ML."""
    from controller.detector import DetectorSettings
    directory = tmp_path_factory.mktemp("fcs")
    settings = StreamSettings(Arrivals(count=60, mix=(("RBC", 0.6), ("melanoma", 0.4)), rate=2000.0, process="poisson"),
                              detector=DetectorSettings(noise_cv=0.6, gate=0.45), model="streamline", seed=5)
    result = run_stream(Scenario(), settings)
    return (write_fcs(directory / "run.fcs", result, settings=settings, scenario=Scenario()),
            write_gatingml(directory / "run.gating.xml", settings.detector.gate), result)


def test_flowkit_applies_the_exported_gate_and_counts_vcytos_classes(exported):
    flowkit = pytest.importorskip("flowkit")
    fcs_path, gate_path, result = exported
    sample = flowkit.Sample(str(fcs_path))
    strategy = flowkit.parse_gating_xml(str(gate_path))
    report = strategy.gate_sample(sample)
    counts = {label: int(report.get_gate_membership(gate_id).sum()) for label, gate_id in GATE_IDS.items()}
    expected = {label: sum(c["detected_class"] == label for c in result["cells"]) for label in GATE_IDS}
    assert counts == expected and min(expected.values()) > 0
    assert result["statistics"]["misclassified"] > 0        # the gate is applied, not the true classes


def test_every_channel_is_bounded_by_its_range_and_described(exported):
    flowkit = pytest.importorskip("flowkit")
    sample = flowkit.Sample(str(exported[0]))
    events = sample.get_events(source="raw")
    metadata = sample.get_metadata()
    for index, name in enumerate(CHANNELS, start=1):
        assert metadata[f"p{index}n"] == name and metadata[f"p{index}s"]
        assert events[:, index - 1].max() <= float(metadata[f"p{index}r"]) and metadata[f"p{index}e"] == "0,0"
    assert float(metadata["p2r"]) <= 10                      # fluorescence of 0-2: a range a logicle display spreads
    assert float(metadata["timestep"]) == 1e-7 and "vcyto" in metadata["cyt"]
    assert re.fullmatch(r"\d\d-[A-Z]{3}-\d{4}", metadata["date"]) and re.fullmatch(r"\d\d:\d\d:\d\d", metadata["btim"])
    assert metadata["vcyto_detector_gate"] == "0.45" and metadata["vcyto_channel_um"] == "300x220"


def test_scatter_is_scatter_and_fluorescence_is_the_detectors_value(exported):
    """FlowKit classifies FSC-A as scatter and FL1-A as fluorescence (channel names as analysis tools expect);
    FL1-A holds the detector's float64 fluorescence, bit for bit, in event order."""
    flowkit = pytest.importorskip("flowkit")
    fcs_path, _, result = exported
    sample = flowkit.Sample(str(fcs_path))
    names = sample.pnn_labels
    assert [names[i] for i in sample.scatter_indices] == ["FSC-A"]
    assert "FL1-A" in [names[i] for i in sample.fluoro_indices] and names[sample.time_index] == "Time"
    assert [sample.pns_labels[i] for i in range(3)] == ["Time", "Fluorescence", "Forward scatter"]
    detected = sorted((c for c in result["cells"] if c["detected_class"]), key=lambda c: c["detection_time_ms"])
    events = sample.get_events(source="raw")
    assert events[:, 1].tolist() == [c["fluorescence"] for c in detected]


def test_fcs_time_ticks_are_exact_over_ten_thousand_seconds(tmp_path):
    """Detection times up to 10^4 s come back from the file within half a tick (0.05 us), where float32
    milliseconds lose ~0.5 ms; FlowKit reads the same times (ticks x $TIMESTEP)."""
    from vcyto.recording.fcs import TIMESTEP, read_fcs
    rng = np.random.default_rng(1)
    times_s = np.sort(np.concatenate([[1e4 - 1.234567e-6, 9999.9999999], rng.uniform(0, 1e4, 200)]))
    cells = [{"detected_class": "I", "detection_time_ms": t * 1e3, "fluorescence": 0.1, "scatter": 80.0,
              "velocity_mm_s": 50.0, "decision": "pass", "outlet": "lower"} for t in times_s]
    path = write_fcs(tmp_path / "long.fcs", {"cells": cells, "model": "rom", "seed": 0})
    _, events, keywords = read_fcs(path)
    assert float(keywords["timestep"]) == TIMESTEP <= 1e-6
    assert np.all(events[:, 0] == np.round(events[:, 0]))                      # integer ticks
    assert np.max(np.abs(events[:, 0] * TIMESTEP - times_s)) <= 0.5 * TIMESTEP + 1e-12
    assert np.max(np.abs(np.float32(times_s * 1e3) * 1e-3 - times_s)) > 1e-4     # what float32 ms would lose
    flowkit = pytest.importorskip("flowkit")
    seconds = flowkit.Sample(str(path)).get_events(source="raw")[:, 0]          # FlowKit scales by $TIMESTEP
    assert np.max(np.abs(seconds - times_s)) <= 0.5 * TIMESTEP + 1e-9


def test_python_m_vcyto_prints_the_version():
    done = subprocess.run([sys.executable, "-m", "vcyto", "--version"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == f"vcyto {__version__}"


def test_the_documented_python_example_runs(tmp_path):
    text = USAGE.read_text()
    section = text.split("## Use from Python", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "purity" in done.stdout and list(tmp_path.glob("*.mcap"))


def test_the_public_api_is_exported():
    import sim
    import vcyto
    for name in vcyto.__all__:
        assert getattr(vcyto, name) is not None
    for name in sim.__all__:
        assert getattr(sim, name) is not None
    assert (Path(vcyto.__file__).parent / "py.typed").exists()
