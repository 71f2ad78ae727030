"""The service guards the bench against hostile or mistyped input: numbers of another JSON type refused in plans,
bench files and request bodies (nothing moves), lone UTF-16 surrogates and deep nesting refused with a 4xx on every
JSON route and in uploads. Real HTTP against the service (uvicorn on loopback) and its simulated bench."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.routing import APIRoute

from calib.errors import InputError
from calib.formats.plan import Plan, make_plan
from drivers.acquisition.config import load_bench
from service.cli import main
from tests.service.conftest import AUTH, make_settings, read_events, start_service, wait_state

API = "/api/v1"
BENCH_SIM = Path(__file__).resolve().parents[2] / "deploy" / "bench-sim.toml"
HEX = "0123456789abcdef0123456789abcdef"
#: the finding's inline plan: a boolean and a numeric string where joint targets (m) belong
MISTYPED_Q = [False, 0.3, "0.3", 0.3]


def _valid_step(service) -> dict:
    nominal = service.app.state.manager.bench.config.nominal_parameters()
    return make_plan("pose-set", nominal, n_fit=4).steps[0].model_dump(exclude_none=True)


def _unmoved(service, q0) -> None:
    mech = service.sim.mechanism
    mech.update()
    assert not any(ax.moving for ax in mech.axes)
    np.testing.assert_allclose(mech.q_true(), q0, atol=1e-9)


# -- numbers must be JSON numbers -------------------------------------------------------------------------------
async def test_inline_plan_with_a_boolean_or_a_numeric_string_is_refused_and_nothing_moves(service):
    c, mech = service.client, service.sim.mechanism
    q0 = mech.q_true().copy()
    good = _valid_step(service)
    cases = [
        ([good, {"phase": "poses", "q": MISTYPED_Q}], ["steps", 1, "q[0]"], "boolean"),
        ([good, {"phase": "poses", "q": [*good["q"][:2], "0.3", good["q"][3]]}], ["steps", 1, "q[2]"], "string"),
        ([{"phase": "poses", "q": [*good["q"][:3], True]}], ["steps", 0, "q[3]"], "boolean"),
    ]
    for steps, loc, kind in cases:
        r = await c.post(f"{API}/runs", json={"plan": {"name": "typed", "steps": steps}, "methods": []}, headers=AUTH)
        assert r.status_code == 422, r.text
        d = r.json()["detail"][0]
        assert d["loc"] == ["body", "plan", *loc] and kind in d["msg"], d
    line = make_plan("line", service.app.state.manager.bench.config.nominal_parameters()).steps[0]
    step = line.model_dump(exclude_none=True)
    step["line"]["samples"] = "11"
    r = await c.post(f"{API}/runs", json={"plan": {"name": "l", "steps": [step]}, "methods": []}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "plan", "steps", 0, "line", "samples"]
    await asyncio.sleep(0.2)
    assert (await c.get(f"{API}/runs")).json() == []
    assert service.app.state.manager.bench_holder is None
    _unmoved(service, q0)


def test_plan_numbers_integers_are_numbers_booleans_and_strings_are_not():
    """JSON ``0`` is a valid joint target (m); ``false`` and ``"0.3"`` are not, each named."""
    plan = Plan.from_dict({"name": "p", "steps": [{"phase": "poses", "q": [0, 0.3, 1, 0.3]}]})
    assert plan.steps[0].q == [0.0, 0.3, 1.0, 0.3]
    with pytest.raises(InputError) as e:
        Plan.from_dict({"name": "p", "steps": [{"phase": "poses", "q": MISTYPED_Q}]}, source="p.json")
    assert e.value.frame == 0 and e.value.field == "q[0]" and "p.json" in str(e.value)
    with pytest.raises(InputError) as e:
        Plan.from_dict({"name": "p", "steps": [{"phase": "poses", "q": [0.1, 0.3, "0.3", 0.3]}]})
    assert e.value.field == "q[2]"


async def test_request_bodies_refuse_booleans_and_numeric_strings_naming_the_field(service):
    c = service.client
    for body, field in (
        ({"max_minutes": True}, "max_minutes"),
        ({"n_fit": "4"}, "n_fit"),
        ({"target_std_m": "5e-4"}, "target_std_m"),
        ({"n_fit": 4.0}, "n_fit"),
        ({"with_line": "false"}, "with_line"),
        ({"seed": False}, "seed"),
    ):
        r = await c.post(f"{API}/plans/design", json=body, headers=AUTH)
        assert r.status_code == 422, (body, r.text)
        assert r.json()["detail"][0]["loc"] == ["body", field], r.text
    r = await c.post(f"{API}/plans/tradeoff", json={"counts": [4, "8"]}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "counts", 1], r.text
    # an integer is a valid number of a float field
    from service.api.plans import DesignBody

    body = DesignBody.model_validate({"max_minutes": 10, "lock_frames": 5})
    assert body.max_minutes == 10.0 and isinstance(body.max_minutes, float)


def api_routes(app) -> list:
    """Every API route of the app (path, methods, body_field, dependant), included routers' routes included."""
    out = []
    for route in app.routes:
        if hasattr(route, "effective_route_contexts"):  # a router included by FastAPI >= 0.16x
            out += list(route.effective_route_contexts())
        elif isinstance(route, APIRoute):
            out.append(route)
    return out


def test_every_request_body_is_strict(service):
    """Every route's JSON body model derives from RequestBody (strict types, no unknown field)."""
    from service.api.deps import RequestBody

    bodies = 0
    for route in api_routes(service.app):
        if route.body_field is not None and route.dependant.body_params:
            model = route.dependant.body_params[0].field_info.annotation
            models = [a for a in getattr(model, "__args__", (model,)) if isinstance(a, type)]
            assert any(issubclass(m, RequestBody) for m in models), (route.path, model)
            bodies += 1
    assert bodies >= 5


async def test_acquire_refuses_a_plan_file_with_a_boolean_q_and_nothing_moves(sim, tmp_path, capsys):
    text = (
        BENCH_SIM.read_text()
        .replace("modbus+tcp://127.0.0.1:5020", sim.actuators_uri)
        .replace('uri = "sim://127.0.0.1:5022"', f'uri = "{sim.camera_uri}"', 1)
        .replace('uri = "sim://127.0.0.1:5022"', f'uri = "{sim.operator_uri}"', 1)
    )
    bench = tmp_path / "bench.toml"
    bench.write_text(text)
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"name": "typed", "steps": [{"phase": "poses", "q": MISTYPED_Q}]}))
    q0 = sim.mechanism.q_true().copy()
    rc = await asyncio.to_thread(main, ["acquire", "--bench", str(bench), "--plan", str(plan), "--out", "ds"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "q[0]" in err and "plan.json" in err and "boolean" in err, err
    assert not (tmp_path / "ds").exists()
    sim.mechanism.update()
    assert not any(ax.moving for ax in sim.mechanism.axes)
    np.testing.assert_allclose(sim.mechanism.q_true(), q0, atol=1e-9)


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ("speed_m_s = 10.0", 'speed_m_s = "10.0"', "actuators.speed_m_s"),
        ("retries = 3", "retries = true", "actuators.retries"),
        ("q_min = [-0.10, -0.10, -0.10, -0.10]", 'q_min = [-0.10, "-0.10", -0.10, -0.10]', "actuators.limits.q_min.1"),
        ("timeout_s = 5.0", 'timeout_s = "5"', "camera.timeout_s"),
    ],
)
def test_bench_file_numbers_must_be_numbers(tmp_path, old, new, field):
    text = BENCH_SIM.read_text()
    assert old in text
    p = tmp_path / "bench.toml"
    p.write_text(text.replace(old, new, 1))
    with pytest.raises(InputError) as e:
        load_bench(p)
    assert e.value.field == field and e.value.file == str(p)
    p.write_text(text.replace("speed_m_s = 10.0", "speed_m_s = 10"))  # a TOML integer is a number
    assert load_bench(p).actuators.speed_m_s == 10.0


# -- lone surrogates, depth -------------------------------------------------------------------------------------
def _write_routes(service) -> list[tuple[str, str]]:
    out = []
    for route in api_routes(service.app):
        for m in route.methods & {"POST", "PUT", "PATCH", "DELETE"}:
            out.append((m, route.path.replace("{run_id}", HEX).replace("{dataset_id}", HEX)))
    return out


async def test_lone_surrogate_is_a_422_on_every_json_route(service):
    c = service.client
    routes = _write_routes(service)
    assert len(routes) >= 8
    bodies = [
        (b'{"note": "\\ud800"}', ["body", "note"]),
        (b'{"plan": {"name": "x\\udfff", "steps": []}}', ["body", "plan", "name"]),
        (b'{"\\ud800": 1}', ["body", "\\ud800"]),
        (b'"\xed\xa0\x80"', ["body"]),  # the surrogate's bytes themselves (not UTF-8)
    ]
    for method, path in routes:
        for body, loc in bodies:
            r = await c.request(method, path, content=body, headers={"Content-Type": "application/json", **AUTH})
            assert r.status_code == 422, (method, path, r.status_code, r.text)
            d = r.json()["detail"][0]
            assert d["type"] == "string_unicode" and d["loc"] == loc, d
    # a body of another content type reaches the route's validation: its 422 is still written
    r = await c.post(f"{API}/runs", content=b'{"note": "\xed\xa0\x80"}', headers={"Content-Type": "text/plain", **AUTH})
    assert 400 <= r.status_code < 500, r.text
    assert (await c.get(f"{API}/runs")).json() == []


async def test_deeply_nested_json_body_is_a_422(service):
    c = service.client
    deep = b"[" * 100_000 + b"]" * 100_000
    r = await c.post(f"{API}/runs", content=deep, headers={"Content-Type": "application/json", **AUTH})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["type"] == "json_depth"
    from service.hardening import MAX_JSON_DEPTH

    nested: object = 1
    for _ in range(MAX_JSON_DEPTH + 1):
        nested = {"a": nested}
    r = await c.post(f"{API}/plans/predict", json={"plan": nested}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["type"] == "json_depth", r.text


def _zip(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return buf.getvalue()


@pytest.mark.parametrize(
    ("doc", "words"),
    [
        (b"[" * 100_000 + b"]" * 100_000, "nested deeper"),
        (b'{"format": "i4cal.dataset/1", "name": "\\ud800", "frames": []}', "surrogate"),
    ],
)
async def test_uploaded_dataset_json_nested_too_deep_or_with_a_surrogate_is_refused(service, doc, words):
    c = service.client
    r = await c.post(
        f"{API}/datasets", content=_zip({"dataset.json": doc}), headers={"Content-Type": "application/zip", **AUTH}
    )
    assert r.status_code == 422, r.text
    msg = r.json()["detail"][0]["msg"]
    assert "dataset.json" in msg and words in msg, msg
    assert list((service.settings.data_dir / "datasets").iterdir()) == []
    assert (await c.get(f"{API}/datasets")).json() == []


async def test_a_run_failing_on_a_non_finite_q_says_so_in_one_line(tmp_path, sim):
    """An uploaded dataset whose dataset.json was changed on disk to hold NaN in a frame's q (NaN cannot come in by
    upload: refused there, below): the offline run fails with one line naming the frame and the field, no
    traceback."""
    from service.design import twin_scene

    cam = tmp_path / "camera.json"
    twin_scene().camera.save(cam)  # known intrinsics: the run gets as far as the frames' q
    service = await start_service(make_settings(tmp_path, sim, camera_file=cam), sim)
    try:
        await _non_finite_q_run(service)
    finally:
        await service.client.aclose()
        await service.stop()


async def _non_finite_q_run(service) -> None:
    c = service.client
    rid = (await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)).json()["id"]
    assert (await wait_state(c, rid))["state"] == "done"
    z = (await c.get(f"{API}/runs/{rid}/dataset")).content
    r = await c.post(f"{API}/datasets", content=z, headers={"Content-Type": "application/zip", **AUTH})
    assert r.status_code == 201, r.text
    ds = r.json()
    meta = next((service.settings.data_dir / "datasets" / ds["id"]).rglob("dataset.json"))
    doc = json.loads(meta.read_text())
    doc["frames"][2]["q"][1] = float("nan")
    meta.write_text(json.dumps(doc))
    r = await c.post(f"{API}/runs", json={"dataset": ds["id"], "methods": ["combined"]}, headers=AUTH)
    assert r.status_code == 202, r.text
    run = await wait_state(c, r.json()["id"])
    assert run["state"] == "failed"
    err = run["error"]
    assert "\n" not in err and "Traceback" not in err and 'File "' not in err, err
    assert "frame 2" in err and "q[1]" in err, err
    # and by upload: refused naming the file, the frame and the field
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for f in meta.parent.rglob("*"):
            if f.is_file():
                zf.write(f, f"dataset/{f.relative_to(meta.parent).as_posix()}")
    r = await c.post(f"{API}/datasets", content=buf.getvalue(), headers={"Content-Type": "application/zip", **AUTH})
    assert r.status_code == 422, r.text
    msg = r.json()["detail"][0]["msg"]
    assert "dataset.json" in msg and "frame 2" in msg and "q[1]" in msg, msg


# -- the server protects the run --------------------------------------------------------------------------------
async def test_every_write_request_needs_a_token_whatever_open_reads(service):
    """Reads are open (the default): every POST, PUT, PATCH and DELETE is still 401 without a valid token, the
    prediction included (seconds of CPU), and nothing runs."""
    assert service.settings.open_reads
    c = service.client
    routes = _write_routes(service)
    assert ("POST", f"{API}/plans/predict") in routes
    for method, path in routes:
        for headers in ({}, {"Authorization": "Bearer wrong"}):
            r = await c.request(method, path, json={}, headers=headers)
            assert r.status_code == 401, (method, path, r.status_code, r.text)
            assert r.headers["www-authenticate"] == "Bearer"
    assert service.app.state.manager.heavy.pending == 0
    assert (await c.get(f"{API}/runs")).json() == []


async def test_probe_needs_a_token_and_never_overlaps_a_run(service, monkeypatch):
    c, manager = service.client, service.app.state.manager
    assert (await c.get(f"{API}/devices", params={"probe": "true"})).status_code == 401
    assert (await c.get(f"{API}/devices")).status_code == 200  # reads stay open
    r = await c.get(f"{API}/devices", params={"probe": "true"}, headers=AUTH)
    assert r.status_code == 200 and r.json()["held_by"] is None
    # a run holds the bench (paused between poses): the probe is refused, no connection is opened
    rid = (await c.post(f"{API}/runs", json={"plan": "full", "methods": []}, headers=AUTH)).json()["id"]
    assert (await c.post(f"{API}/runs/{rid}/pause", headers=AUTH)).status_code == 200
    probes = []
    real_probe = manager.bench.probe

    async def counted_probe(*args, **kwargs):
        probes.append(1)
        return await real_probe(*args, **kwargs)

    monkeypatch.setattr(manager.bench, "probe", counted_probe)
    r = await c.get(f"{API}/devices", params={"probe": "true"}, headers=AUTH)
    assert r.status_code == 409 and rid in r.json()["detail"], r.text
    assert probes == []
    assert (await c.post(f"{API}/runs/{rid}/abort", headers=AUTH)).status_code == 202
    await wait_state(c, rid)
    # while a probe connects (held at its start here, then the real probe), a run cannot start
    go = asyncio.Event()

    async def held_probe(*args, **kwargs):
        await go.wait()
        return await real_probe(*args, **kwargs)

    monkeypatch.setattr(manager.bench, "probe", held_probe)
    probing = asyncio.create_task(c.get(f"{API}/devices", params={"probe": "true"}, headers=AUTH))
    for _ in range(200):
        if manager.probing:
            break
        await asyncio.sleep(0.01)
    r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
    assert r.status_code == 409 and "probed" in r.json()["detail"], r.text
    go.set()
    assert (await probing).status_code == 200
    r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
    assert r.status_code == 202, r.text
    assert (await wait_state(c, r.json()["id"]))["state"] == "done"


def _nice(pid: int) -> int:
    import os

    return os.getpriority(os.PRIO_PROCESS, pid)


async def test_heavy_requests_run_in_a_niced_child_with_a_bounded_queue(service):
    """A prediction runs in another process, niced above the run's extraction and fits (job_niceness), one at a
    time; with the queue full the next one gets 429 with Retry-After, and those admitted all finish."""
    import os

    c, pool = service.client, service.app.state.manager.heavy
    pool.max_waiting = 1  # 1 computing + 1 waiting; a third is refused
    body = {"plan": "rotation-sweep", "methods": ["combined"]}
    first = asyncio.create_task(c.post(f"{API}/plans/predict", json=body, headers=AUTH))
    for _ in range(1000):
        if pool.running and pool.running[0].process.pid is not None:
            break
        await asyncio.sleep(0.01)
    pid = pool.running[0].process.pid
    assert pid != os.getpid()
    for _ in range(500):  # the child renices itself first thing
        if _nice(pid) > _nice(os.getpid()):
            break
        await asyncio.sleep(0.01)
    assert pool.running and pool.running[0].process.pid == pid  # still computing
    assert _nice(pid) > _nice(os.getpid()) and _nice(pid) > service.settings.job_niceness, (_nice(pid), pid)
    second = asyncio.create_task(c.post(f"{API}/plans/predict", json=body, headers=AUTH))
    for _ in range(500):
        if pool.pending == 2:
            break
        await asyncio.sleep(0.01)
    r = await c.post(f"{API}/plans/predict", json=body, headers=AUTH)
    assert r.status_code == 429, r.text
    assert int(r.headers["retry-after"]) >= 1
    r1, r2 = await first, await second
    assert r1.status_code == 200 and r2.status_code == 200, (r1.text, r2.text)
    assert r1.json()["predicted_std_m"] == r2.json()["predicted_std_m"]
    assert pool.pending == 0 and pool.running == [] and pool.noise is not None


# -- smaller items ------------------------------------------------------------------------------------------------
def test_token_expires_in_counts_from_issuance(tmp_path, capsys, monkeypatch):
    """``--expires-in 3s`` lives 3 s from the token's creation, however long the database takes to open (a slow
    open, migrations on first use: made slow here by 1.5 s before the real upgrade). Before, the 3 s were counted
    from the command's start: the token lived 0.44 s."""
    import time

    from sqlalchemy import select

    from service.db import Database, Token

    real_upgrade = Database.upgrade

    def slow_upgrade(self, *args, **kwargs):
        time.sleep(1.5)
        return real_upgrade(self, *args, **kwargs)

    monkeypatch.setattr(Database, "upgrade", slow_upgrade)
    data = tmp_path / "data"
    assert main(["token", "create", "--data-dir", str(data), "--expires-in", "3s"]) == 0
    assert "expires" in capsys.readouterr().err
    db = Database(f"sqlite:///{data / 'i4cal.db'}")
    try:
        with db.session() as s:
            row = s.scalars(select(Token)).one()
            lifetime = (row.expires_at - row.created_at).total_seconds()
    finally:
        db.dispose()
    assert abs(lifetime - 3.0) < 0.01, lifetime


async def _paused_run(c) -> str:
    """A run acquiring the 'full' plan, paused between two poses (it holds the bench and stays active)."""
    rid = (await c.post(f"{API}/runs", json={"plan": "full", "methods": []}, headers=AUTH)).json()["id"]
    async with asyncio.timeout(60):
        while True:
            r = await c.post(f"{API}/runs/{rid}/pause", headers=AUTH)
            if r.status_code == 200:
                return rid
            assert (await c.get(f"{API}/runs/{rid}")).json()["state"] in ("queued", "acquiring")
            await asyncio.sleep(0.01)


async def test_a_duplicate_resume_or_pause_is_a_409_and_no_event(service):
    c = service.client
    rid = await _paused_run(c)
    assert (await c.post(f"{API}/runs/{rid}/pause", headers=AUTH)).status_code == 409
    codes = [(await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)).status_code for _ in range(3)]
    assert codes == [202, 409, 409], codes
    run = await wait_state(c, rid)
    assert run["state"] == "done", run
    evs = await read_events(c, rid)
    assert [e["type"] for e in evs].count("resumed") == 1 and [e["type"] for e in evs].count("paused") == 1


async def _read_until_overflow(resp, got: list[dict], emit) -> None:
    """Read a stream's events into ``got``; once the past is read (the ``paused`` event), emit a burst of 40."""
    kind = None
    async for line in resp.aiter_lines():
        if line.startswith("event: "):
            kind = line[7:]
        elif line.startswith("data: "):
            ev = json.loads(line[6:])
            got.append({**ev, "type": "overflow"} if kind == "overflow" else ev)
            if ev.get("type") == "paused":
                for _ in range(40):
                    emit()


async def test_a_slow_event_subscriber_is_told_to_reconnect_and_recovers_every_event(service, monkeypatch):
    """The live queue of a subscriber holds 3 events here; 40 come at once (a burst: the stream cannot send any
    in between). The stream sends an ``overflow`` event and ends; reconnecting with Last-Event-ID gives the rest:
    every event once, in order."""
    from service.runs import events as events_mod

    c, manager = service.client, service.app.state.manager
    rid = await _paused_run(c)
    monkeypatch.setattr(events_mod, "SUBSCRIBER_QUEUE_MAX", 3, raising=False)
    got: list[dict] = []
    with contextlib.suppress(TimeoutError):  # before: the stream went on, silently short of events
        async with asyncio.timeout(15), c.stream("GET", f"{API}/runs/{rid}/events") as resp:
            await _read_until_overflow(resp, got, lambda: manager.emit(rid, "burst", {}))
    overflow = next((e for e in got if e.get("type") == "overflow"), None)
    got = [e for e in got if e.get("type") != "overflow"]
    assert overflow is not None and overflow["data"]["last_seq"] == got[-1]["seq"], (overflow, got[-1])
    last = got[-1]["seq"]
    async with c.stream(
        "GET", f"{API}/runs/{rid}/events", params={"follow": "false"}, headers={"Last-Event-ID": str(last)}
    ) as resp:
        async for line in resp.aiter_lines():
            if line.startswith("data: "):
                got.append(json.loads(line[6:]))
    seqs = [e["seq"] for e in got]
    assert seqs == list(range(1, len(seqs) + 1)), seqs
    assert len([e for e in got if e["type"] == "burst"]) == 40
    assert (await c.post(f"{API}/runs/{rid}/abort", headers=AUTH)).status_code == 202
    await wait_state(c, rid)
