"""Text and enum fields of any request, checked without a daemon: the message names the field
by its path in the request."""

from __future__ import annotations

import pytest

from matopt_api.v1 import matopt_pb2 as pb
from matoptd.server import fields
from matoptd.errors import InvalidArgument


def refused(request) -> str:
    with pytest.raises(InvalidArgument) as err:
        fields.check(request)
    return str(err.value)


def test_sane_requests_pass():
    fields.check(pb.CreateJobRequest(
        spec=pb.JobSpec(scene="scenes/abc", loss=pb.LOSS_DUAL_BUFFER, schedule=pb.SCHEDULE_CONSTANT,
                        references=[pb.Reference(blob="blobs/" + "a" * 64, filename="r.exr")],
                        parameters=[pb.ParameterSpec(key="red.reflectance.value")]),
        request_id="r-1", initial_from_which=pb.WHICH_LAST))
    fields.check(pb.CreateSceneRequest(overrides={"resx": "32"}, display_name="x" * 256))


@pytest.mark.parametrize("request_,message", [
    (pb.CreateJobRequest(spec=pb.JobSpec(schedule=99)),
     "spec.schedule 99 is not a Schedule: expected one of SCHEDULE_COSINE (1), "
     "SCHEDULE_CONSTANT (2)"),
    (pb.CreateJobRequest(spec=pb.JobSpec(sensor_mode=99)), "spec.sensor_mode 99 is not a "
     "SensorMode: expected one of SENSOR_MODE_ACCUMULATE (1), SENSOR_MODE_STEP_PER_SENSOR (2)"),
    (pb.CreateJobRequest(spec=pb.JobSpec(loss=-1)), "spec.loss -1 is not a Loss"),
    (pb.GetJobResultRequest(name="jobs/a", which=99), "which 99 is not a Which"),
    (pb.ListJobsRequest(state=99), "state 99 is not a JobState"),
])
def test_unknown_enum_values_name_field_and_value(request_, message):
    assert refused(request_).startswith(message)


@pytest.mark.parametrize("request_,message", [
    (pb.GetJobRequest(name="jobs/a\0b"), "name contains a NUL byte: 'jobs/a\\0b'"),
    (pb.CreateJobRequest(spec=pb.JobSpec(parameters=[pb.ParameterSpec(key="a"),
                                                     pb.ParameterSpec(key="b\0")])),
     "spec.parameters[1].key contains a NUL byte"),
    (pb.CreateSceneRequest(files=[pb.BundleFile(path="x\0.obj")]),
     "files[0].path contains a NUL byte"),
    (pb.CreateSceneRequest(overrides={"resx": "3\0"}), "overrides['resx'] contains a NUL"),
    (pb.CreateSceneRequest(overrides={"re\0sx": "3"}), "a key of overrides contains a NUL"),
    (pb.GetJobRequest(name="a" * 300), "name is 300 characters long; at most 128"),
    (pb.CreateSceneRequest(display_name="d" * 300), "display_name is 300 characters long; "
     "at most 256"),
    (pb.CreateJobRequest(request_id="r" * 300), "request_id is 300 characters long"),
    (pb.CreateSceneRequest(overrides={"k": "v" * 5000}), "overrides['k'] is 5,000 characters"),
    (pb.FindMissingBlobsRequest(sha256=["a" * 64, "b" * 65]), "sha256[1] is 65 characters"),
])
def test_text_fields_without_nul_and_within_length(request_, message):
    assert refused(request_).startswith(message)
