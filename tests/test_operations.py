"""What an operator sees of matoptd: --help, the config file and its precedence, tokens read
again on SIGHUP while a job runs, JSON logs, and Prometheus metrics scraped during a job."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import grpc
import pytest

from matopt_api.v1 import matopt_pb2 as pb
from matoptd import options

from conftest import TOKENS, Daemon, Stubs, token_file, wait_iteration, wait_state
from scenes import cornell_with_truth

CAROL = "carol-token-0123456789ab"


def matoptd(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "matoptd", *args], capture_output=True,
                          text=True, timeout=120, **kw)


# -- --help and precedence, without a daemon ---------------------------------------------------

def test_help_describes_every_flag_and_lists_the_variables():
    out = matoptd("--help").stdout
    flags = set(re.findall(r"\[(--[a-z-]+)", out.split("\n\n")[0]))  # the usage's
    assert {"--tls-cert", "--tls-key", "--log-level", "--config", "--metrics-port"} <= flags
    for flag in flags - {"--version"}:
        # "  --flag METAVAR   text" or the text on the next line
        described = re.search(rf"^  {flag}\b[^\n]*?(?: {{2,}}|\n {{10,}})(\S[^\n]*)", out, re.M)
        assert described and len(described.group(1)) > 10, flag
        variable = "MATOPTD_" + flag[2:].replace("-", "_").upper()
        assert re.search(rf"^  {variable} +{flag}$", out, re.M), variable
    assert "command line > environment > config file" in out


def test_command_line_beats_environment_beats_config_file(tmp_path):
    (tmp_path / "conf").mkdir()
    config = tmp_path / "conf" / "matoptd.toml"
    config.write_text('workers = 2\nmax-jobs-per-user = 3\ndata_dir = "state"\n'
                      'max-film-memory = "1G"\nwatchdog = 30\n')
    environ = {"MATOPTD_CONFIG": str(config), "MATOPTD_WORKERS": "4", "MATOPTD_QUOTA": ""}
    args = options.parse_args([], environ)
    assert (args.workers, args.max_jobs_per_user, args.max_film_memory) == (4, 3, 1 << 30)
    assert args.data_dir == tmp_path / "conf" / "state"  # from the file's folder
    assert args.watchdog == 30.0 and args.quota is None  # an empty variable is unset
    args = options.parse_args(["--workers", "5", "--data-dir", "here"], environ)
    assert (args.workers, args.data_dir, args.max_jobs_per_user) == (5, Path("here"), 3)
    assert options.parse_args([], {}).max_jobs_per_user == 16  # the default


@pytest.mark.parametrize("text, message", [
    ('max-job-per-user = 3\n',
     "unknown key 'max-job-per-user' (did you mean 'max-jobs-per-user'?)"),
    ('workers = "two"\n', "'workers': invalid value 'two' for --workers"),
    ('log-level = "loud"\n', "'log_level': 'loud' for --log-level is not one of debug"),
    ('[server]\nlisten = "x"\n', "unknown key 'server'"),
    ('listen = \n', "not valid TOML"),
])
def test_a_bad_config_file_is_refused_naming_file_and_key(tmp_path, text, message):
    config = tmp_path / "matoptd.toml"
    config.write_text(text)
    done = matoptd("--config", str(config), "--data-dir", str(tmp_path / "data"))
    assert done.returncode == 2
    assert str(config) in done.stderr and message in done.stderr, done.stderr
    assert not (tmp_path / "data").exists()  # refused before anything started


def test_a_bad_environment_variable_is_refused_naming_it(tmp_path):
    done = matoptd("--data-dir", str(tmp_path / "data"),
                   env={**os.environ, "MATOPTD_MAX_SAMPLES": "many"})
    assert done.returncode == 2
    assert "MATOPTD_MAX_SAMPLES: invalid value 'many' for --max-samples" in done.stderr


# -- one daemon, set up by a config file -------------------------------------------------------

@pytest.fixture(scope="module")
def operated(tmp_path_factory):
    """A daemon whose tokens, limits, JSON logs and metrics come from a config file; the
    command line overrides --max-film-side."""
    root = tmp_path_factory.mktemp("operated")
    token_file(root)  # alice and bob, at root/tokens
    (root / "matoptd.toml").write_text(
        'tokens = "tokens"\nlog-format = "json"\nmetrics_port = 0\nmax-samples = 100000\n'
        "max-film-side = 48\n")
    d = Daemon(root / "data", None, "--config", str(root / "matoptd.toml"),
               "--max-film-side", "64").start()
    yield d
    d.stop()


def log_lines(d: Daemon) -> list[dict]:
    return [json.loads(line) for line in d.log.read_text().splitlines() if line.strip()]


def metrics_url(d: Daemon) -> str:
    for line in log_lines(d):
        found = re.search(r"metrics on (http://\S+)", line["message"])
        if found:
            return found.group(1)
    raise AssertionError("no metrics address in the log")


def scrape(d: Daemon) -> dict[str, float]:
    """Every sample of /metrics, by its name and labels as written."""
    with urllib.request.urlopen(metrics_url(d), timeout=10) as r:
        text = r.read().decode()
    return {line.rsplit(" ", 1)[0]: float(line.rsplit(" ", 1)[1])
            for line in text.splitlines() if line and not line.startswith("#")}


def small_job(stubs: Stubs, iterations: int) -> pb.Job:
    """A 32 px Cornell box's red wall, from a reference of the scene itself: fast steps."""
    scene, _, ref = cornell_with_truth(stubs, 32, 8, ())
    spec = pb.JobSpec(scene=scene.name, iterations=iterations, spp=4,
                      references=[pb.Reference(blob=ref.exr_blob)],
                      parameters=[pb.ParameterSpec(key="red.reflectance.value")])
    return stubs.jobs.CreateJob(pb.CreateJobRequest(spec=spec))


def test_config_file_limits_apply_and_the_command_line_wins(operated):
    alice = Stubs(operated.address, TOKENS["alice"])  # the file's relative tokens path
    scene = alice.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "56",
                                                                      "resy": "56"}))
    # 56 px: over the file's max-film-side 48, within the command line's 64.
    assert alice.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=4)).images
    with pytest.raises(grpc.RpcError) as err:  # the file's max-samples
        alice.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=64))
    assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "the limit is 100,000 (matoptd --max-samples)" in err.value.details()
    big = alice.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "100",
                                                                    "resy": "100"}))
    with pytest.raises(grpc.RpcError) as err:
        alice.scenes.RenderScene(pb.RenderSceneRequest(name=big.name, spp=1))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "at most 64 px on a side" in err.value.details()
    alice.close()


def test_sighup_reloads_tokens_and_running_jobs_go_on(operated):
    alice = Stubs(operated.address, TOKENS["alice"])
    bob, carol = Stubs(operated.address, TOKENS["bob"]), Stubs(operated.address, CAROL)
    assert bob.server.GetServerInfo(pb.GetServerInfoRequest()).user == "bob"
    job = small_job(alice, 40)
    before = wait_iteration(alice, job.name, 2).iteration

    tokens = operated.data_dir.parent / "tokens"
    token_file(tokens.parent, {"alice": TOKENS["alice"], "carol": CAROL})  # bob removed
    operated.proc.send_signal(signal.SIGHUP)
    deadline = time.time() + 30
    while True:  # the signal is handled between calls: the first call may precede it
        try:
            assert carol.server.GetServerInfo(pb.GetServerInfoRequest()).user == "carol"
            break
        except grpc.RpcError as exc:
            assert exc.code() == grpc.StatusCode.UNAUTHENTICATED
            assert time.time() < deadline, "carol's token never became valid"
            time.sleep(0.2)
    with pytest.raises(grpc.RpcError) as err:
        bob.server.GetServerInfo(pb.GetServerInfoRequest())
    assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED

    # The job never noticed: it goes on from where it was, to the end.
    assert wait_iteration(alice, job.name, before + 2).iteration >= before + 2
    done = wait_state(alice, job.name, {pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED})
    assert done.state == pb.JOB_STATE_SUCCEEDED and done.iteration == 40

    # A file that cannot be used keeps the table in use, and the log says where it is wrong.
    tokens.write_text(f"{TOKENS['alice']} alice\nnot-a-pair\n")
    operated.proc.send_signal(signal.SIGHUP)
    deadline = time.time() + 30
    while not any("tokens not reloaded" in line["message"] for line in log_lines(operated)):
        assert time.time() < deadline, "no error logged for the bad tokens file"
        time.sleep(0.2)
    error = next(line for line in log_lines(operated) if "tokens not reloaded" in line["message"])
    assert error["level"] == "ERROR" and f"{tokens}:2: expected 'TOKEN USER'" in error["message"]
    assert carol.server.GetServerInfo(pb.GetServerInfoRequest()).user == "carol"
    for s in (alice, bob, carol):
        s.close()


def test_metrics_during_a_job(operated):
    alice = Stubs(operated.address, TOKENS["alice"])
    # Frozen iterations of 32 px take ~10 ms: long enough to be running at the scrape.
    n = 600
    job = small_job(alice, n)
    wait_iteration(alice, job.name, 3)
    now = scrape(operated)
    at = alice.jobs.GetJob(pb.GetJobRequest(name=job.name)).iteration  # at least the scrape's
    # The job is running, and so counted: by phase, and as alice's.
    assert now['matoptd_jobs{phase="running"}'] >= 1
    # ... and as alice's one job, running or between its turns (queued): the scheduler may
    # have given another user's job the worker at the scrape's moment.
    assert sum(now[f'matoptd_user_jobs{{phase="{p}",user="alice"}}']
               for p in ("queued", "running")) == 1
    iterations = now['matoptd_worker_iterations_total{worker="workers/0"}']
    assert iterations >= 3
    assert now['matoptd_queue_wait_seconds_count'] >= 1
    assert 0 < now['matoptd_worker_memory_bytes{worker="workers/0"}'] \
        <= now['matoptd_worker_memory_limit_bytes{worker="workers/0"}']
    assert now['matoptd_worker_restarts_total{worker="workers/0"}'] == 0
    get_job = '{code="OK",method="matopt.v1.JobService/GetJob"}'
    assert now[f"matoptd_rpc_duration_seconds_count{get_job}"] >= 1
    assert 0 < now[f"matoptd_rpc_duration_seconds_sum{get_job}"] \
        < 5 * now[f"matoptd_rpc_duration_seconds_count{get_job}"]

    done = wait_state(alice, job.name, {pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED})
    assert done.state == pb.JOB_STATE_SUCCEEDED
    after = scrape(operated)
    assert after['matoptd_worker_iterations_total{worker="workers/0"}'] >= iterations + n - at
    assert after['matoptd_jobs{phase="succeeded"}'] >= 1
    refused = '{code="UNAUTHENTICATED",method="matopt.v1.ServerService/GetServerInfo"}'
    stranger = Stubs(operated.address, "no-such-token-0123456789")
    with pytest.raises(grpc.RpcError):
        stranger.server.GetServerInfo(pb.GetServerInfoRequest())
    stranger.close()
    assert scrape(operated)[f"matoptd_rpc_duration_seconds_count{refused}"] >= 1
    alice.close()


def test_every_log_line_is_json_and_job_lines_name_job_and_user(operated):
    lines = log_lines(operated)  # raises on a line that is not JSON
    assert lines and all({"time", "level", "logger", "message"} <= set(line) for line in lines)
    admitted = [line for line in lines if " admitted: " in line["message"]]
    assert admitted and all(line["user"] == "alice" and line["job"].startswith("jobs/")
                            for line in admitted)
    ended = [line for line in lines if " SUCCEEDED at iteration " in line["message"]]
    assert ended and ended[0]["user"] == "alice"


def test_the_example_config_file_names_every_key_and_parses(tmp_path):
    example = Path(__file__).resolve().parent.parent / "deploy" / "matoptd.toml.example"
    lines = [m.group(1) for m in re.finditer(r"^#([a-z][a-z-]* = .*)$", example.read_text(),
                                            re.M)]
    assert {line.split(" = ")[0].replace("-", "_") for line in lines} == options.CONFIG_KEYS
    every = tmp_path / "matoptd.toml"
    every.write_text("\n".join(lines) + "\n")  # each setting uncommented
    args = options.parse_args(["--config", str(every)], {})
    assert (args.workers, args.max_film_memory, args.log_format) == (2, 4 << 30, "json")
    assert args.tokens == tmp_path / "tokens"


def test_a_metric_that_fails_is_logged_and_left_out(caplog):
    from prometheus_client import generate_latest
    from matoptd.server.metrics import Metrics

    class LostStore:
        def count_by_phase(self):
            raise OSError("database is locked")

    metrics = Metrics(LostStore())
    metrics.stepped("workers/0", 3)
    text = generate_latest(metrics.registry).decode()  # the scrape still answers
    assert 'matoptd_worker_iterations_total{worker="workers/0"} 3.0' in text
    assert "matoptd_jobs{" not in text
    assert "database is locked" in caplog.text and "_jobs failed" in caplog.text
    metrics.iterations = None  # a counter gone wrong: the job's step must not notice
    metrics.stepped("workers/0", 1)
    assert "Metrics.stepped failed" in caplog.text


def test_a_workers_own_output_becomes_log_records(caplog):
    from matoptd import logs
    caplog.set_level("WARNING")
    proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.stderr.write("
                             "'Traceback (most recent call last):\\n  boom\\n')"],
                            stderr=subprocess.PIPE)
    logs.relay(proc.stderr, "matoptd.workers.7")
    proc.wait()
    deadline = time.time() + 10
    while len(caplog.records) < 2 and time.time() < deadline:
        time.sleep(0.05)
    assert [(r.name, r.getMessage()) for r in caplog.records] == [
        ("matoptd.workers.7", "Traceback (most recent call last):"),
        ("matoptd.workers.7", "  boom")]
    line = json.loads(logs.JsonFormatter().format(caplog.records[1]))
    assert line["logger"] == "matoptd.workers.7" and line["level"] == "WARNING"
