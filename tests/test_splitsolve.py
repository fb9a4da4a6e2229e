"""The split solve (sim/splitsolve.py): exact to round-off, a true separator, and bit-for-bit reproducible
across processes, down to the recordings of a stream with the default numerics."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim.fluid import NavierStokes
from sim.linalg import Pardiso, pardiso_available
from sim.scenario import UM, Scenario

pytestmark = pytest.mark.skipif(not pardiso_available(), reason="the split solve runs on MKL PARDISO")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def fluid():
    return NavierStokes(Scenario().with_numerics(mesh_h=10 * UM, linear_solver="pardiso"))


def test_split_solve_equals_the_sequential_solve_to_round_off(fluid):
    from sim.splitsolve import SplitPardiso
    matrix = fluid.constant_matrix()
    split = SplitPardiso(matrix, fluid.free_x)
    left, right, separator = split.parts
    assert len(left) + len(right) + len(separator) == matrix.shape[0]
    assert abs(matrix[left][:, right]).sum() == 0                 # a true separator
    assert 0.3 < len(left) / (len(left) + len(right)) < 0.7 and len(separator) < 0.05 * matrix.shape[0]
    rhs = np.random.default_rng(1).standard_normal(matrix.shape[0])
    solution = split.solve(rhs)
    assert np.linalg.norm(matrix @ solution - rhs) <= 1e-13 * np.linalg.norm(rhs)
    reference = Pardiso(matrix, symmetric=True).solve(rhs)
    assert np.linalg.norm(solution - reference) <= 1e-12 * np.linalg.norm(reference)
    assert np.array_equal(split.solve(rhs), solution)             # same input, same bits


SCRIPT = """
import hashlib, numpy as np
from sim.fluid import NavierStokes
from sim.scenario import UM, Scenario
fluid = NavierStokes(Scenario().with_numerics(mesh_h=5 * UM))
state = fluid.steady(0.0)
for _ in range(5):
    state = fluid.step(state, actuation=1.0)
factor = fluid._constant.factor
print(type(factor).__name__, type(factor.inner).__name__, hashlib.sha256(state.velocity.tobytes()).hexdigest())
"""


def test_default_steps_are_bit_identical_in_two_processes():
    outputs = [subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, cwd=ROOT,
                              check=True).stdout.split() for _ in range(2)]
    # 5 um: ~24,000 unknowns; the default is the split solve in single precision, refined in double
    assert outputs[0][:2] == ["MixedPrecision", "SplitPardiso"]
    assert outputs[0] == outputs[1]


def _scrub(message):
    """A decoded Foxglove message with its wall-clock timestamps cleared (log times start at the run's wall-clock
    start; the simulated time is in every message)."""
    for field, value in message.ListFields():
        if field.message_type is None:
            continue
        if field.message_type.full_name == "google.protobuf.Timestamp":
            message.ClearField(field.name)
        elif field.is_repeated:
            for item in value:
                _scrub(item)
        else:
            _scrub(value)
    return message.SerializeToString()


def mcap_content(path):
    """Every message of a recording, wall-clock fields aside: (topic, log time from the first, content)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory
    decode = DecoderFactory()
    content, origin = [], None
    with open(path, "rb") as handle:
        for schema, channel, message in make_reader(handle).iter_messages(log_time_order=False):
            origin = message.log_time if origin is None else origin
            if channel.message_encoding == "json":
                data = {k: v for k, v in json.loads(message.data).items() if k not in ("wall_time", "diagnostics")}
            else:
                data = _scrub(decode.decoder_for(channel.message_encoding, schema)(message.data))
            content.append((channel.topic, message.log_time - origin, data))
    return content


def test_two_feib_streams_give_identical_recordings(tmp_path):
    """The paper's mesh (the split solve), a melanoma for 0.5 ms: every message equal, wall clock aside."""
    environment = {**os.environ, "VCYTO_CACHE": "off"}
    recordings = []
    for run in ("a", "b"):
        output = tmp_path / run
        result = subprocess.run([sys.executable, "-m", "vcyto.cli", "stream", "--cells", "melanoma", "--dt", "25us",
                                 "--max-time", "0.5", "--allow-partial", "--no-viewer", "--quiet", "--output",
                                 str(output)],
                                capture_output=True, text=True, cwd=ROOT, env=environment)
        assert result.returncode == 0, result.stderr
        recordings.append(next(output.glob("*.mcap")))
    first, second = (mcap_content(path) for path in recordings)
    assert len([m for m in first if m[0] == "/loop/step"]) == 20
    assert first == second
