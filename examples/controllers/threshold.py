"""A controller of one's own in 20 lines: sort every event brighter than a threshold, abort nothing.

    vcyto stream --model rom --cells RBC,melanoma,RBC,melanoma \
        --controller-from examples/controllers/threshold.py:Threshold
"""

from controller.events import Decision


class Threshold:
    """Sorts an event whose fluorescence reaches ``threshold``: one calibrated pulse, timed from its velocity."""

    name = "threshold"

    def __init__(self, settings, threshold: float = 0.5):
        self.settings, self.threshold = settings, threshold

    def on_event(self, event, clock):
        s = self.settings
        arrival = event.time + s.delay * s.reference_velocity / event.velocity
        if event.fluorescence < self.threshold:
            return [Decision(event.event_id, "pass", arrival)]
        on = max(arrival - s.lead, clock)          # no pulse can start before the decision
        return [Decision(event.event_id, "sort", arrival, on, on + s.pulse)]
