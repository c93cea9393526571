"""Silent wrong answers (issue 35, item 6): a filter that lost track, times below the float spacing, and
a sensor with a sustained bias — in the library, `yauyau filter`, `yauyau check` and a real
`yauyau serve` process.  docs/reliability.md ("Model checks that protect users from wrong numbers")
lists what each test proves.

The truth in these tests is independent of the code under test: a state held at x = 12 outside a ball
of radius 7 (a filter that answers healthy estimates there is wrong, whatever they are), times that a
float cannot tell apart, observations simulated from the model itself (no alarm is due) or shifted by a
constant (an alarm is due), and the false-alarm rate of the CUSUM charts measured on standard normal
scores against Siegmund's formula.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import httpx
import numpy as np
import pytest
from helpers import EXAMPLES
from helpers.server import Server
from yauyau.solver.errors import InputError
from yauyau.solver.spec import spec_from_dict

import yauyau

PROBLEM = "application/problem+json"
OU7 = {"name": "ou-radius-7", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x"],
       "initial": {"kind": "gaussian", "mean": [1.0], "cov": [[0.5]]}, "domain": {"radius": 7.0},
       "discretization": {"dt": 0.01, "basis": 96}}  # examples/ou.toml on the radius of the attack
# a discrete sensor z = x + v, sd 0.1, every 0.05, on the OU dynamics (Kalman–Bucy: no ball)
OU_SENSOR = {"name": "ou-discrete-sensor", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x"],
             "observation_noise": [[0.01]], "measurement": {"kind": "discrete"},
             "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]}, "domain": {"radius": 7.0},
             "discretization": {"dt": 0.05, "basis": 96}}
# The 0.33 bias case (docs/reliability.md): the power meter (z = x² + v, sd 0.5) reading 0.33 low; x² cannot
# follow readings below 0, so its innovations stay mostly on one side
BIAS = -0.33
MONITOR = 1e9  # healthy rows per false alarm: the setting docs/reliability.md measures
BIAS_BOUND = 3000  # rows: generous over the measured delays (docs/reliability.md: median 507, longest 732)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    directory = tmp_path_factory.mktemp("watch-store")
    ids = {"ou7": yauyau.precompute(spec_from_dict(OU7), directory),
           "sensor": yauyau.precompute(spec_from_dict(OU_SENSOR), directory),
           "power": yauyau.precompute(EXAMPLES / "power_meter.toml", directory)}
    return directory, ids


def held_at(x: float, rows: int, seed: int = 1, dt: float = 0.01) -> np.ndarray:
    """Increments of a state held at ``x``: dy = x dt + dw, R = 1."""
    return x * dt + np.random.default_rng(seed).normal(0.0, math.sqrt(dt), (rows, 1))


def cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "yauyau.service.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=600)


def is_problem(response: httpx.Response, status: int, field: str) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith(PROBLEM)
    body = response.json()
    assert body["field"] == field, body
    return body


def lost_reason_is_actionable(reason: str) -> None:
    assert reason.startswith("lost track"), reason
    assert "domain.follow = true" in reason and "domain.radius" in reason, reason


# -- lost track ----------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_state_outside_the_ball_is_lost_track_not_healthy_estimates(store):
    """The attack: OU on radius 7, increments of x = 12, on_degenerate = reinitialise.  It restarted on
    every row (1 128 restarts in 2 000 rows) and answered estimates inside the ball flagged healthy."""
    directory, ids = store
    flt = yauyau.open_filter(directory, ids["ou7"], method="yau-yau", on_degenerate="reinitialise")
    result = flt.run(held_at(12.0, 2000))
    bad = result.degenerate
    assert bad.any(), "estimates of a state outside the ball answered as healthy"
    first = int(np.argmax(bad))
    assert bad[first:].all() and first < 400  # from the lost row on, every row
    assert result.reinitialised.sum() <= 2  # the third restart within 100 rows is the lost one
    lost_reason_is_actionable(result.reason)
    assert flt.lost == result.reason and flt.degenerate
    # a lost filter stays lost, computes nothing, and keeps its time
    again = flt.run(held_at(12.0, 50, seed=2))
    assert again.degenerate.all() and np.all(np.diff(again.t) > 0) and again.t[0] == pytest.approx(20.01)
    estimate = flt.step([0.12])
    assert estimate.degenerate and estimate.reason.startswith("lost track")
    # the state (with the watch) survives a round trip, JSON included
    copy = yauyau.open_filter(directory, ids["ou7"], method="yau-yau", on_degenerate="reinitialise")
    copy.restore(json.loads(json.dumps(flt.state_dict())))
    assert copy.lost == flt.lost and copy.run(held_at(12.0, 5)).degenerate.all()
    # and recovers: reinitialise clears the count (from "last", near the rim, it may soon lose track
    # again; from a prior where the state is, it does not), and so does reset
    copy.reinitialise("last")
    assert copy.lost is None and not copy.degenerate
    copy.reinitialise({"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]})
    assert not copy.run(held_at(0.0, 200)).degenerate.any() and copy.lost is None
    flt.reset()
    assert flt.lost is None and not flt.run(held_at(0.0, 200)).degenerate.any()


@pytest.mark.slow
def test_a_run_of_gated_rows_is_lost_track_on_a_filter_without_a_ball(store):
    """Kalman–Bucy has no ball: a sensor that jumps to readings of 12 is gated row after row (the filter
    only predicts) and its estimates stay near 0: after 20 consecutive gated rows it has lost track."""
    directory, ids = store
    flt = yauyau.open_filter(directory, ids["sensor"])
    assert flt.method == "kalman-bucy"
    sim = yauyau.simulate(spec_from_dict(OU_SENSOR), 100, seed=3)
    rows = np.concatenate([sim.observations, np.full((60, 1), 12.0)])
    rows[110] = np.nan  # a row without an observation neither counts nor breaks the run
    result = flt.run(rows)
    assert not result.degenerate[:100].any() and result.gated[100:110].all() and result.gated[111:121].all()
    assert not result.degenerate[:120].any() and result.degenerate[120:].all()  # the 20th gated row: 120
    assert result.reason.startswith("lost track: 20 consecutive observations gated")
    assert "no domain ball" in result.reason and "check the model and the sensor" in result.reason
    # a shorter run is not lost, and the count starts again after a used observation
    flt = yauyau.open_filter(directory, ids["sensor"])
    result = flt.run(np.concatenate([sim.observations, np.full((19, 1), 12.0), sim.observations[-5:],
                                     np.full((19, 1), 12.0)]))
    assert result.gated.sum() == 38 and not result.degenerate.any() and flt.lost is None


@pytest.mark.slow
def test_the_same_model_with_the_state_inside_the_ball_is_not_flagged(store):
    directory, ids = store
    for rows in (held_at(3.0, 2000), yauyau.simulate(spec_from_dict(OU7), 2000, seed=4).increments):
        flt = yauyau.open_filter(directory, ids["ou7"], method="yau-yau", on_degenerate="reinitialise")
        result = flt.run(rows)
        assert not result.degenerate.any() and not result.reinitialised.any() and not result.gated.any()
        assert flt.lost is None


@pytest.mark.slow
def test_filter_command_exits_3_naming_the_domain_when_the_state_leaves_the_ball(store, tmp_path):
    directory, ids = store
    source = tmp_path / "dy.csv"
    source.write_text("\n".join(repr(float(v)) for v in held_at(12.0, 1000)[:, 0]) + "\n")
    out = tmp_path / "out.csv"
    run = cli("filter", ids["ou7"], "--store", directory, "--increments", source, "--out", out,
              "--method", "yau-yau", "--on-degenerate", "reinitialise")
    assert run.returncode == 3, run.stderr
    assert "lost track" in run.stderr and "domain.follow = true" in run.stderr
    assert "--on-degenerate reinitialise starts again instead" not in run.stderr
    lines = out.read_text().splitlines()
    columns = lines[0].split(",")
    flags = np.array([int(line.split(",")[columns.index("degenerate")]) for line in lines[1:]])
    first = int(np.argmax(flags))
    assert flags[first:].all() and 0 < first < 400
    # the state inside the ball: exit 0, nothing flagged
    source.write_text("\n".join(repr(float(v)) for v in held_at(3.0, 1000)[:, 0]) + "\n")
    run = cli("filter", ids["ou7"], "--store", directory, "--increments", source, "--out", out,
              "--method", "yau-yau", "--on-degenerate", "reinitialise")
    assert run.returncode == 0, run.stderr


@pytest.mark.slow
def test_check_fails_a_spec_whose_paths_leave_the_ball(tmp_path):
    """A drift that pushes out (x grows like e^(t/2)) on a ball of radius 6: simulated paths cross the rim."""
    spec = tmp_path / "outward.json"
    spec.write_text(json.dumps({**OU7, "name": "outward", "drift": ["0.5*x"], "domain": {"radius": 6.0},
                                "discretization": {"dt": 0.01, "basis": 48}}))
    run = cli("check", spec, "--json", "--steps", "600")
    assert run.returncode == 1, run.stderr
    report = json.loads(run.stdout)
    assert report["ok"] is False and report["left_domain"] > 0
    assert "domain.follow = true" in report["domain"]
    assert "radius 6" in report["domain"] and "domain.radius" in report["domain"]
    run = cli("check", spec, "--steps", "600")
    assert run.returncode == 1 and "simulated paths" in run.stdout and "leave the domain ball" in run.stdout


# -- time below the float spacing -------------------------------------------------------------------
@pytest.mark.slow
def test_times_whose_steps_floats_cannot_hold_are_refused_in_the_library(store):
    directory, ids = store
    for t0 in (1e16, 1e308, -1e16):
        with pytest.raises(InputError) as refused:
            yauyau.open_filter(directory, ids["ou7"], method="yau-yau", t0=t0)
        assert refused.value.field == "t0" and "nearer origin" in refused.value.message
    sensor = yauyau.open_filter(directory, ids["sensor"])
    for times in ([1e16, 1e16 + 1], [1e16, 1e16 + 16]):
        with pytest.raises(InputError) as refused:
            sensor.run([[0.1], [0.2]], times=times)
        assert refused.value.field == "times[1]"
    assert sensor.state.step == 0  # nothing applied
    late = yauyau.open_filter(directory, ids["sensor"], t0=1e6)  # a large time with a fine step: accepted
    assert list(late.run([[0.1], [0.2]], times=[1e6 + 0.05, 1e6 + 0.1]).t) == [1e6 + 0.05, 1e6 + 0.1]
    flt = yauyau.open_filter(directory, ids["ou7"], method="yau-yau", t0=1e6)
    t = np.concatenate([flt.run(held_at(0.0, 300, seed=s)).t for s in range(3)])
    assert np.all(np.diff(t) > 0) and t[-1] == pytest.approx(1e6 + 9.0, abs=1e-6)


@pytest.mark.slow
def test_times_below_the_float_spacing_over_the_command_line(store, tmp_path):
    directory, ids = store
    source = tmp_path / "dy.csv"
    source.write_text("0.01\n0.02\n")
    out = tmp_path / "out.csv"
    for t0 in ("1e16", "1e308"):
        run = cli("filter", ids["ou7"], "--store", directory, "--increments", source, "--out", out,
                  "--t0", t0)
        assert run.returncode == 2 and "error: t0: --t0 = " in run.stderr and "Traceback" not in run.stderr, \
            run.stderr
    timed = tmp_path / "timed.csv"
    timed.write_text("t,z\n1e16,0.1\n10000000000000016,0.2\n")
    run = cli("filter", ids["sensor"], "--store", directory, "--observations", timed, "--out", out, "--t0", 0)
    assert run.returncode == 2 and "times[1]" in run.stderr and "line 3" in run.stderr, run.stderr
    assert not out.exists()
    run = cli("filter", ids["ou7"], "--store", directory, "--increments", source, "--out", out, "--t0", "1e6")
    assert run.returncode == 0, run.stderr
    t = [float(line.split(",")[1]) for line in out.read_text().splitlines()[1:]]
    assert t[1] > t[0] > 1e6


# -- the innovation monitor -------------------------------------------------------------------------
@pytest.mark.slow
def test_monitor_raises_the_alarm_on_a_biased_sensor(store):
    """The 0.33 bias case: the power meter's readings 0.33 low.  Before, nothing flagged it (the gate
    passes every row); now the alarm comes within the bound, on the side of the bias."""
    directory, ids = store
    sim = yauyau.simulate(EXAMPLES / "power_meter.toml", BIAS_BOUND, seed=5)
    assert yauyau.open_filter(directory, ids["power"]).watch_settings.monitor == 0  # off unless asked for
    flt = yauyau.open_filter(directory, ids["power"], monitor=MONITOR)
    result = flt.run(sim.observations + BIAS)
    assert not result.gated.any() and not result.degenerate.any()  # nothing else says so
    assert result.alarm.any(), f"no alarm in {BIAS_BOUND} rows"
    first = int(np.argmax(result.alarm))
    assert result.monitor[first] <= -1.0  # −: the observations are below their predictions
    assert flt.watch.alarms == int(result.alarm.sum())
    # a bias the filter can take for the state is slower to show (docs/reliability.md): the OU sensor
    # reading 0.33 high, whose mean ends 0.33 off, within 40 000 rows (measured: median 12 851)
    sim = yauyau.simulate(spec_from_dict(OU_SENSOR), 40_000, seed=5)
    result = yauyau.open_filter(directory, ids["sensor"], monitor=MONITOR).run(sim.observations + 0.33)
    first = int(np.argmax(result.alarm))
    assert result.alarm.any() and result.monitor[first] >= 1.0
    assert np.mean(result.mean[:first, 0] - sim.states[1:first + 1, 0]) > 0.2  # the wrong answer it flags


@pytest.mark.slow
def test_monitor_stays_quiet_on_healthy_streams(store):
    """Rows simulated from the model itself: 10 000 of the power meter, 20 000 of the OU sensor, 5 000 of
    the engine on the OU ball: no alarm.  At 1e9 healthy rows per false alarm the chance of
    one in these 35 000 rows is about 3.5e-5 (Siegmund's approximation, conservative by a third as
    measured below); the seeds are fixed, so the test is deterministic."""
    directory, ids = store
    for key, spec, rows, seed in (("power", yauyau.load_spec(EXAMPLES / "power_meter.toml"), 10_000, 6),
                                  ("sensor", spec_from_dict(OU_SENSOR), 20_000, 6),
                                  ("ou7", spec_from_dict(OU7), 5000, 7)):
        flt = yauyau.open_filter(directory, ids[key], method="yau-yau" if key == "ou7" else None,
                                 monitor=MONITOR)
        result = flt.run(yauyau.simulate(spec, rows, seed=seed).rows)
        assert not result.alarm.any() and np.abs(result.monitor).max() < 1.0, key
    off = yauyau.open_filter(directory, ids["sensor"], monitor=0)
    biased = off.run(yauyau.simulate(spec_from_dict(OU_SENSOR), 2000, seed=5).observations + 3.0)
    assert not biased.alarm.any() and np.isnan(biased.monitor).all()  # off is off


def test_monitor_false_alarm_rate_matches_its_setting():
    """The charts on standard normal scores at 1e3 and 1e4 rows per false alarm (where alarms are many
    enough to count): the measured rate is within a factor 2 of the setting, as Siegmund's formula
    promises for a two-sided CUSUM (docs/reliability.md)."""
    from yauyau.solver.watch import run_charts

    rng = np.random.default_rng(11)
    for target, rows in ((1e3, 400_000), (1e4, 2_000_000)):
        _, _, alarm = run_charts((), rng.normal(size=(rows, 1)), target)
        assert 0.5 * target < rows / alarm.sum() < 2.0 * target, (target, alarm.sum())


@pytest.mark.slow
def test_monitor_columns_on_the_command_line_only_when_it_is_on(store, tmp_path):
    """`yauyau filter --monitor 1e9` on the power meter reading 0.33 low: the columns alarm and monitor,
    an alarm row at +-1, and stderr naming the first; without --monitor the columns of the filter
    without the monitor; on the unbiased readings, stderr says no alarm."""
    directory, ids = store
    sim = yauyau.simulate(EXAMPLES / "power_meter.toml", BIAS_BOUND, seed=5)
    times = sim.times[1:len(sim.observations) + 1]

    def observations(name, rows):
        path = tmp_path / name
        pairs = zip(times.tolist(), rows[:, 0].tolist(), strict=True)
        path.write_text("t,z\n" + "".join(f"{t!r},{z!r}\n" for t, z in pairs))
        return path

    biased = observations("biased.csv", sim.observations + BIAS)
    out = tmp_path / "out.csv"
    run = cli("filter", ids["power"], "--store", directory, "--observations", biased, "--out", out,
              "--monitor", "1e9")
    assert run.returncode == 0, run.stderr
    lines = out.read_text().splitlines()
    columns = lines[0].split(",")
    assert columns[-2:] == ["alarm", "monitor"]
    table = [line.split(",") for line in lines[1:]]
    alarms = [k for k, row in enumerate(table) if row[columns.index("alarm")] == "1"]
    assert alarms, "no alarm on the command line"
    assert float(table[alarms[0]][columns.index("monitor")]) <= -1.0  # below: the readings are low
    assert f"{len(alarms)} alarm(s), the first at step {alarms[0] + 1}" in run.stderr
    assert "drifted below their predictions" in run.stderr
    run = cli("filter", ids["power"], "--store", directory, "--observations", biased, "--out", out)
    assert run.returncode == 0 and "innovation monitor" not in run.stderr, run.stderr
    assert out.read_text().splitlines()[0].split(",") == columns[:-2]
    healthy = observations("healthy.csv", sim.observations)
    run = cli("filter", ids["power"], "--store", directory, "--observations", healthy, "--out", out,
              "--monitor", "1e9")
    assert run.returncode == 0, run.stderr
    assert "innovation monitor: no alarm (1,000,000,000 healthy rows per false alarm)" in run.stderr


@pytest.mark.slow
def test_monitor_state_round_trips_and_continues(store):
    """Half a biased stream, the state through JSON into a new filter, the other half: the same alarms and
    statistic as one uninterrupted run, bit for bit (the charts' sums are exact)."""
    directory, ids = store
    rows = yauyau.simulate(EXAMPLES / "power_meter.toml", 3000, seed=5).observations + BIAS
    whole = yauyau.open_filter(directory, ids["power"], monitor=MONITOR)
    expected = whole.run(rows)
    assert expected.alarm.any()
    first = yauyau.open_filter(directory, ids["power"], monitor=MONITOR)
    part = first.run(rows[:250])
    saved = json.loads(json.dumps(first.state_dict()))
    assert saved["watch"]["charts"] and saved["watch"]["statistic"] == part.monitor[-1]
    assert abs(part.monitor[-1]) > 0.1  # the charts had climbed: the restored ones must carry on
    second = yauyau.open_filter(directory, ids["power"], monitor=MONITOR)
    second.restore(saved)
    rest = second.run(rows[250:])
    assert np.array_equal(np.concatenate([part.monitor, rest.monitor]), expected.monitor)
    assert np.array_equal(np.concatenate([part.alarm, rest.alarm]), expected.alarm)
    assert second.watch == whole.watch
    for bad, field in (({"charts": [-1.0]}, "state.watch.charts"),
                       ({"gated_run": "3"}, "state.watch.gated_run")):
        with pytest.raises(InputError) as refused:
            second.restore({**saved, "watch": {**saved["watch"], **bad}})
        assert refused.value.field == field


# -- over HTTP, a real server ---------------------------------------------------------------------
def _session(url, model, **body) -> dict:
    r = httpx.post(f"{url}/v1/sessions", json={"model": model, **body}, timeout=60)
    assert r.status_code == 201, r.text
    return r.json()


def _chunk(url, sid, seq, **body) -> httpx.Response:
    return httpx.post(f"{url}/v1/sessions/{sid}/observations", json={"seq": seq, **body}, timeout=120)


def _metric(url, name) -> float:
    text = httpx.get(f"{url}/metrics", timeout=30).text
    return sum(float(line.split()[-1]) for line in text.splitlines() if line.startswith(name + " "))


@pytest.mark.service
@pytest.mark.slow
def test_silent_wrong_answers_over_http(store, tmp_path):
    """A real server: the lost track (rows degenerate with the reason; a reset recovers), t0 and times
    below the float spacing (422 naming the field), and the monitor (alarm rows, the metric, its state
    kept across a SIGKILL and a restart, a replay byte for byte)."""
    directory, ids = store
    db = tmp_path / "sessions.sqlite3"
    server = Server(directory, db)
    try:
        url = server.url
        # lost track
        created = _session(url, ids["ou7"], method="yau-yau", on_degenerate="reinitialise")
        assert "lost_track" not in created["options"]  # the default rule (20, 3, 100): not listed
        sid, rows, flagged = created["id"], held_at(12.0, 1000), []
        for seq in range(10):
            r = _chunk(url, sid, seq, increments=rows[100 * seq:100 * seq + 100].tolist())
            assert r.status_code == 200, r.text
            flagged += [bool(row.get("degenerate")) for row in r.json()["estimates"]]
        first = flagged.index(True)
        assert all(flagged[first:]) and first < 400
        reason = r.json()["reason"]
        lost_reason_is_actionable(reason)
        info = httpx.get(f"{url}/v1/sessions/{sid}", timeout=30).json()
        assert info["lost"] == reason and info["estimate"]["degenerate"]
        assert _metric(url, "yauyau_lost_track_chunks_total") >= 1
        r = httpx.post(f"{url}/v1/sessions/{sid}/reset", json={"seq": 10, "from": "last"}, timeout=60)
        assert r.status_code == 200, r.text
        info = httpx.get(f"{url}/v1/sessions/{sid}", timeout=30).json()
        assert info["lost"] is None and not info["estimate"]["degenerate"]
        inside = _session(url, ids["ou7"], method="yau-yau", on_degenerate="reinitialise")["id"]
        r = _chunk(url, inside, 0, increments=held_at(3.0, 1000).tolist())
        assert r.status_code == 200 and not r.json()["degenerate"]
        assert not any(row.get("degenerate") for row in r.json()["estimates"])
        # time below the float spacing
        for t0 in (1e16, 1e308):
            is_problem(httpx.post(f"{url}/v1/sessions", json={"model": ids["ou7"], "t0": t0}, timeout=30),
                       422, "t0")
        timed = _session(url, ids["sensor"])["id"]
        for times in ([1e16, 1e16 + 1], [1e16, 1e16 + 16]):
            is_problem(_chunk(url, timed, 0, observations=[[0.1], [0.2]], times=times), 422, "times[1]")
        late = _session(url, ids["ou7"], method="yau-yau", t0=1e6)
        t = []
        for seq in range(3):
            r = _chunk(url, late["id"], seq, increments=held_at(0.0, 100, seed=seq).tolist())
            t += [row["t"] for row in r.json()["estimates"]]
        assert np.all(np.diff(t) > 0) and t[0] > 1e6
        # the monitor
        assert "monitor" not in _session(url, ids["power"])["options"]  # off unless asked for
        biased = _session(url, ids["power"], monitor=MONITOR)
        assert biased["options"]["monitor"] == MONITOR
        observations = yauyau.simulate(EXAMPLES / "power_meter.toml", BIAS_BOUND, seed=5).observations + BIAS
        alarms, seq, bodies = [], 0, []
        while not alarms and seq < BIAS_BOUND // 250:
            r = _chunk(url, biased["id"], seq, observations=observations[250 * seq:250 * seq + 250].tolist())
            assert r.status_code == 200, r.text
            body = r.json()
            bodies.append(r.content)
            alarms = body["alarms"]
            seq += 1
        assert alarms, "no alarm over HTTP"
        row = body["estimates"][alarms[0]]
        assert row["alarm"] is True and row["monitor"] <= -1.0
        assert _metric(url, "yauyau_monitor_alarms_total") >= 1
        before = httpx.get(f"{url}/v1/sessions/{biased['id']}", timeout=30).json()
        assert before["monitor"]["alarms"] == len(alarms)
        server.kill()
        server = Server(directory, db)
        url = server.url
        after = httpx.get(f"{url}/v1/sessions/{biased['id']}", timeout=30).json()
        assert after["monitor"] == before["monitor"] and after["lost"] is None
        replay = _chunk(url, biased["id"], seq - 1,
                        observations=observations[250 * (seq - 1):250 * seq].tolist())
        assert replay.status_code == 200 and replay.content == bodies[-1]
        # a session that asks for no monitor gets none
        quiet = _session(url, ids["power"], monitor=0, lost_track={"gated": 0, "restarts": 0})
        assert "monitor" not in quiet["options"]
        assert quiet["options"]["lost_track"] == {"gated": 0, "restarts": 0, "window": 100}
        r = _chunk(url, quiet["id"], 0, observations=(observations[:2000] - 0.5).tolist())
        assert r.status_code == 200 and r.json()["alarms"] == [] and r.json()["monitor"] is None
        is_problem(httpx.post(f"{url}/v1/sessions", json={"model": ids["sensor"], "monitor": 5}, timeout=30),
                   422, "monitor")
    finally:
        server.kill()


@pytest.mark.slow
def test_bundled_examples_keep_their_model_ids(tmp_path):
    """The new [measurement] monitor is left out of a spec's id where it has its default (off); a spec
    that sets it gets its monitor in every filter opened on it."""
    from yauyau.storage.model_store import model_id

    spec = yauyau.load_spec(EXAMPLES / "power_meter.toml")
    assert "monitor" not in spec.canonical_json()
    doc = spec.model_dump(mode="json")
    doc["measurement"]["monitor"] = 1e6
    assert model_id(spec_from_dict(doc).canonical_json()) != model_id(spec.canonical_json())
    with pytest.raises(Exception, match="measurement.monitor"):
        spec_from_dict({**doc, "measurement": {**doc["measurement"], "monitor": 10}})
    flt = yauyau.open_filter(tmp_path, yauyau.precompute(spec_from_dict(doc), tmp_path))
    assert flt.watch_settings.monitor == 1e6 and yauyau.open_filter(tmp_path, model_id(
        spec_from_dict(doc).canonical_json()), monitor=0).watch_settings.monitor == 0
