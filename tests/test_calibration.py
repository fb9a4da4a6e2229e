import pytest

from sim.method.calibration import calibrate_streaming_force


@pytest.mark.slow
def test_default_streaming_force_is_the_calibrated_one(paper_scenario):
    """Re-run the calibration of docs/physics.md, "SAW models" (about a dozen steady solves at paper resolution)."""
    force, exit_y, _ = calibrate_streaming_force(paper_scenario)
    assert force == pytest.approx(paper_scenario.saw.streaming_force, rel=0.05)
