"""The daemon's named lists agree with the API's enums, and the daemon's own process reads the
loss declarations without loading the renderer."""

from __future__ import annotations

import subprocess
import sys

from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb
from matoptd.engine.losses import LOSSES, OBJECTIVES
from matoptd.settings import SCHEDULES, SENSOR_MODES


def test_every_objective_loss_is_an_api_value_and_every_api_value_a_loss():
    assert sorted(OBJECTIVES) == sorted(enums.short_names(pb.Loss))
    # The diagnostic one is declared, and kept out of the API (its enum value is reserved).
    assert not LOSSES["mean_bias_error"].objective
    assert all(loss.title and loss.renders >= 1 for loss in LOSSES.values())


def test_schedules_and_sensor_modes_are_the_api_values():
    assert list(SCHEDULES) == enums.short_names(pb.Schedule)
    assert list(SENSOR_MODES) == enums.short_names(pb.SensorMode)


def test_the_server_reads_the_loss_declarations_without_drjit_or_mitsuba():
    code = ("import sys\n"
            "import matoptd.server.admission, matoptd.server.info_service\n"
            "from matoptd.engine.losses import LOSSES\n"
            "assert LOSSES['dual_buffer'].renders == 2\n"
            "loaded = [m for m in ('drjit', 'mitsuba') if m in sys.modules]\n"
            "assert not loaded, loaded\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
