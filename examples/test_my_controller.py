"""A closed-loop sorting test of one's own controller, as a user writes it: `pytest examples/test_my_controller.py`.

The fixture ``sort_run`` and the assertions come with vcyto (its pytest plugin, vcyto/testing.py).
"""

from controller.events import Decision
from vcyto.testing import assert_no_missed_deadlines, assert_outlets, assert_purity


class Brightest:
    """Sort every event whose fluorescence reaches 0.5, with the calibrated pulse; pass the others."""

    def __init__(self, settings):
        self.settings = settings

    def on_event(self, event, clock):
        s = self.settings
        arrival = event.time + s.delay * s.reference_velocity / event.velocity
        if event.fluorescence < 0.5:
            return [Decision(event.event_id, "pass", arrival)]
        return [Decision(event.event_id, "sort", arrival, arrival - s.lead, arrival - s.lead + s.pulse)]


def test_melanoma_up_rbc_down(sort_run):
    run = sort_run(Brightest, cells=["RBC", "melanoma", "RBC", "melanoma"])
    assert_outlets(run, melanoma="upper", RBC="lower")


def test_pure_at_a_thousand_cells_per_second(sort_run):
    run = sort_run(Brightest, count=400, mix=[("RBC", 0.8), ("melanoma", 0.2)], rate=1000, arrivals="poisson")
    assert_purity(run, at_least=0.99)
    assert_no_missed_deadlines(run)
