"""Service hardening (input bounds, archive unpacking, security headers, Host allow-list), over real HTTP
against the service (uvicorn on loopback) and its simulated bench."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import re
import struct
import tarfile
import threading
import time
import zipfile
from pathlib import Path

import pytest

from calib.formats.plan import MAX_LINE_SAMPLES, MAX_PLAN_FRAMES, MAX_PLAN_STEPS, make_plan
from service.api.datasets import CHUNK_BYTES, ArchiveError, ArchiveTooLargeError, unpack_archive
from service.hardening import CSP_DOCS
from tests.service.conftest import AUTH, make_settings, start_service

API = "/api/v1"
JSON = {"Content-Type": "application/json", **AUTH}


def _nominal(service):
    return service.app.state.manager.bench.config.nominal_parameters()


def _valid_steps(service, n: int) -> list[dict]:
    """``n`` steps cycling over a valid pose set of the service's bench."""
    base = [s.model_dump(exclude_none=True) for s in make_plan("pose-set", _nominal(service), n_fit=50).steps]
    return [base[i % len(base)] for i in range(n)]


def _line_step(service, samples: int) -> dict:
    step = make_plan("line", _nominal(service)).steps[0].model_dump(exclude_none=True)
    step["line"]["samples"] = samples
    return step


# -- finding 4: plan sizes bounded, validated off the event loop -----------------------------------------------
async def test_huge_line_refused_at_once_naming_the_field(service):
    """The 1e6-sample line (froze the event loop for 127 s) is refused in well under a second, naming the field;
    so are more steps than allowed and a plan over the frame budget."""
    c = service.client
    plan = {"name": "huge", "steps": [_valid_steps(service, 1)[0], _line_step(service, 1_000_000)]}
    t0 = time.perf_counter()
    r = await c.post(f"{API}/runs", json={"plan": plan, "methods": []}, headers=AUTH, timeout=10.0)
    took = time.perf_counter() - t0
    assert r.status_code == 422, r.text
    d = r.json()["detail"][0]
    assert d["loc"] == ["body", "plan", "steps", 1, "line", "samples"] and str(MAX_LINE_SAMPLES) in d["msg"]
    assert took < 2.0, took
    # more steps than MAX_PLAN_STEPS: refused on the count, before any step is looked at
    plan = {"name": "many", "steps": _valid_steps(service, MAX_PLAN_STEPS + 1)}
    r = await c.post(f"{API}/runs", json={"plan": plan, "methods": []}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "plan", "steps"], r.text
    # every line within its bound, but the total over MAX_PLAN_FRAMES: the step that passes the budget is named
    n_lines = MAX_PLAN_FRAMES // MAX_LINE_SAMPLES + 1
    plan = {"name": "long", "steps": [_line_step(service, MAX_LINE_SAMPLES)] * n_lines}
    r = await c.post(f"{API}/runs", json={"plan": plan, "methods": []}, headers=AUTH)
    assert r.status_code == 422, r.text
    d = r.json()["detail"][0]
    assert d["loc"] == ["body", "plan", "steps", n_lines - 1, "line", "samples"] and str(MAX_PLAN_FRAMES) in d["msg"]
    assert service.app.state.manager.bench_holder is None and (await c.get(f"{API}/runs")).json() == []


async def test_plan_at_its_size_bounds_validates_quickly_and_names_the_last_step(service):
    """MAX_PLAN_STEPS steps, the last one outside the soft limits: the whole plan is checked (vectorised) and the
    422 names that step; nothing starts."""
    c = service.client
    steps = _valid_steps(service, MAX_PLAN_STEPS)
    steps[-1] = {**steps[-1], "q": [*steps[-1]["q"][:3], 5.0]}
    t0 = time.perf_counter()
    r = await c.post(f"{API}/runs", json={"plan": {"name": "big", "steps": steps}, "methods": []}, headers=AUTH)
    took = time.perf_counter() - t0
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["body", "plan", "steps", MAX_PLAN_STEPS - 1, "q[3]"]
    assert took < 5.0, took  # 0.9 s step by step before, ~0.1 s vectorised (2 shared cores)


async def test_plan_validation_does_not_block_the_event_loop(service, monkeypatch):
    """While a plan is validated, /healthz answers at once. The validation is made slow on purpose (a wrapper that
    sleeps 1.5 s around the real one: what a slow validation does to the loop, deterministic on a busy machine);
    run in the handler, as before, it held every other request for its whole duration."""
    import calib.formats.plan

    real = calib.formats.plan.validate_plan
    seen: dict[str, object] = {}

    def slow_validate(*a, **kw):
        seen["thread"] = threading.current_thread()
        time.sleep(1.5)
        return real(*a, **kw)

    monkeypatch.setattr(calib.formats.plan, "validate_plan", slow_validate)
    c = service.client
    steps = _valid_steps(service, 200)
    steps[-1] = {**steps[-1], "q": [*steps[-1]["q"][:3], 5.0]}
    post = asyncio.create_task(
        c.post(f"{API}/runs", json={"plan": {"name": "slow", "steps": steps}, "methods": []}, headers=AUTH)
    )
    await asyncio.sleep(0.3)  # the validation is under way
    lat = []
    while not post.done():
        t0 = time.perf_counter()
        assert (await c.get("/healthz")).status_code == 200
        lat.append(time.perf_counter() - t0)
        await asyncio.sleep(0.05)
    r = await post
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][-2:] == [199, "q[3]"], r.text
    assert seen["thread"] is not threading.main_thread()
    assert len(lat) >= 5 and max(lat) < 0.5, lat  # blocked: one poll of >= 1.2 s


# -- finding 6: NaN / Infinity never a 500 -----------------------------------------------------------------------
@pytest.mark.parametrize(
    ("body", "loc"),
    [
        (b'{"plan": "full", "methods": [], "note": NaN}', ["body", "note"]),
        (b'{"plan": "full", "methods": [], "bench": Infinity}', ["body", "bench"]),
        (b'{"plan": {"name": "x", "steps": [{"phase": "poses", "q": [0.3, -Infinity, 0.3, 0.3]}]}}', None),
        (b'{"plan": {"name": "x", "steps": [{"phase": "poses", "q": [0.3, NaN, 0.3, 0.3]}]}}', None),
        (b'{"plan": {"name": "x", "steps": [{"phase": "poses", "q": [0.3, 1e999, 0.3, 0.3]}]}}', None),
    ],
)
async def test_non_finite_numbers_are_422_naming_the_field(service, body, loc):
    c = service.client
    r = await c.post(f"{API}/runs", content=body, headers=JSON)
    assert r.status_code == 422, r.text
    d = r.json()["detail"][0]
    assert d["loc"] == (loc or ["body", "plan", "steps", 0, "q", 1]), d
    assert d["type"] == "finite_number" and isinstance(d["input"], str)
    assert (await c.get(f"{API}/runs")).json() == [] and service.app.state.manager.bench_holder is None


async def test_validation_error_with_a_non_finite_input_is_serialisable():
    """The 422 handler itself: an error whose input is NaN (a validation error raised anywhere) is written as JSON
    (FastAPI's own handler raised 'Out of range float values are not JSON compliant': a 500)."""
    from fastapi.exceptions import RequestValidationError

    from service.hardening import validation_error_handler

    exc = RequestValidationError(
        [{"type": "string_type", "loc": ("body", "note"), "msg": "Input should be a valid string", "input": [1e400]}]
    )
    r = await validation_error_handler(None, exc)  # type: ignore[arg-type]
    assert r.status_code == 422
    assert json.loads(r.body)["detail"][0]["input"] == ["inf"]


async def test_json_bodies_are_bounded(tmp_path, sim):
    svc = await start_service(make_settings(tmp_path, sim, max_json_body_bytes=10_000), sim)
    try:
        r = await svc.client.post(f"{API}/runs", content=b'{"note": "' + b"x" * 20_000 + b'"}', headers=JSON)
        assert r.status_code == 413 and "max_json_body_bytes" in r.text
    finally:
        await svc.client.aclose()
        await svc.stop()


def _zip(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as zf:
        for k, v in members.items():
            zf.writestr(k, v)
    return buf.getvalue()


async def test_zip_member_with_a_bad_crc_is_422_naming_it(service):
    data = bytearray(
        _zip({"dataset/dataset.json": b"{}", "dataset/frames/000001.png": b"A" * 4000}, zipfile.ZIP_STORED)
    )
    i = data.index(b"A" * 4000)
    data[i + 1000] ^= 0xFF  # one byte of the member's data: its CRC-32 no longer matches
    r = await service.client.post(
        f"{API}/datasets", content=bytes(data), headers={"Content-Type": "application/zip", **AUTH}
    )
    assert r.status_code == 422, r.text
    assert "dataset/frames/000001.png" in r.text and "CRC" in r.text
    data_dir = service.settings.data_dir
    assert list((data_dir / "datasets").iterdir()) == [] and list((data_dir / "tmp").iterdir()) == []


# -- finding 10: archive extraction bounded by the bytes written -------------------------------------------------
MIB = 1 << 20


def _written(dest: Path) -> int:
    return sum(f.stat().st_size for f in dest.rglob("*") if f.is_file()) if dest.exists() else 0


def _many_member_bomb(n: int, size: int) -> bytes:
    """A real zip bomb: ``n`` members of ``size`` zero bytes each (~1 KiB compressed per MiB), sizes declared."""
    buf = io.BytesIO()
    zero = bytes(size)
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for k in range(n):
            zf.writestr(f"dataset/frames/{k:06d}.png", zero)
    return buf.getvalue()


def _lying_zip(actual: int, declared: int) -> bytes:
    """One deflated member of ``actual`` zero bytes whose local header and central directory declare ``declared``."""
    data = bytearray(_zip({"dataset/big.bin": bytes(actual)}))
    for sig, off in ((b"PK\x03\x04", 22), (b"PK\x01\x02", 24)):
        i = data.index(sig)
        assert struct.unpack_from("<I", data, i + off)[0] == actual
        struct.pack_into("<I", data, i + off, declared)
    return bytes(data)


def _tar_gz_bomb(n: int, size: int) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", compresslevel=9) as tf:
        for k in range(n):
            ti = tarfile.TarInfo(f"dataset/frames/{k:06d}.png")
            ti.size = size
            tf.addfile(ti, io.BytesIO(bytes(size)))
    return buf.getvalue()


def test_zip_bomb_declaring_more_than_the_limit_writes_nothing(tmp_path):
    """40 members of 1 MiB (57 KiB compressed), limit 4 MiB: refused before a byte is written (the old code wrote up
    to the limit, member after member, before refusing: 3.95 GiB with the default 4 GiB limit)."""
    limit = 4 * MIB
    for name, archive in (("bomb.zip", _many_member_bomb(40, MIB)), ("bomb.tar.gz", _tar_gz_bomb(40, MIB))):
        assert len(archive) < 200_000
        src = tmp_path / name
        src.write_bytes(archive)
        dest = tmp_path / f"out-{name}"
        with pytest.raises(ArchiveTooLargeError, match="max_unpacked_bytes") as err:
            unpack_archive(src, dest, max_bytes=limit, max_members=1000)
        assert "dataset/frames/" in str(err.value)
        assert _written(dest) == 0, name


def test_lying_declared_sizes_never_take_more_than_the_limit_to_disk(tmp_path):
    """Declared sizes are not trusted: a member declaring 1 MiB that inflates to 64 MiB is cut at what it declares
    (then refused, corrupt); at most the limit ever reaches the disk; a limit smaller than one chunk holds too."""
    src = tmp_path / "lie.zip"
    src.write_bytes(_lying_zip(64 * MIB, MIB))
    assert src.stat().st_size < 100_000
    for limit in (4 * MIB, MIB + 1):
        dest = tmp_path / f"lie-{limit}"
        with pytest.raises(ArchiveError, match="dataset/big.bin"):
            unpack_archive(src, dest, max_bytes=limit, max_members=10)
        assert _written(dest) <= min(limit, MIB)
    # the counting itself: a budget below the honest total stops before the chunk that would pass it
    src.write_bytes(_zip({"dataset/a.bin": bytes(3 * CHUNK_BYTES)}))
    from service.api import datasets

    budget = [2 * CHUNK_BYTES + 10]
    with zipfile.ZipFile(src) as zf, zf.open("dataset/a.bin") as f, pytest.raises(ArchiveTooLargeError, match="a.bin"):
        datasets._copy_limited(f, tmp_path / "a.bin", budget, "dataset/a.bin")
    assert (tmp_path / "a.bin").stat().st_size == 2 * CHUNK_BYTES


async def test_zip_bomb_upload_refused_naming_the_limit_nothing_left(tmp_path, sim):
    svc = await start_service(make_settings(tmp_path, sim, max_unpacked_bytes=4 * MIB), sim)
    c = svc.client
    data = tmp_path / "data"
    peak = [0]
    stop = threading.Event()

    def watch() -> None:  # the data directory's size while the upload is handled
        while not stop.is_set():
            with contextlib.suppress(FileNotFoundError):
                peak[0] = max(peak[0], _written(data / "datasets"))
            time.sleep(0.002)

    w = threading.Thread(target=watch)
    w.start()
    try:
        for body, ctype in (
            (_many_member_bomb(64, MIB), "application/zip"),
            (_tar_gz_bomb(64, MIB), "application/gzip"),
        ):
            r = await c.post(f"{API}/datasets", content=body, headers={"Content-Type": ctype, **AUTH})
            assert r.status_code == 422, r.text
            assert "max_unpacked_bytes" in r.text and "dataset/frames/" in r.text
        assert list((data / "datasets").iterdir()) == [] and list((data / "tmp").iterdir()) == []
    finally:
        stop.set()
        w.join()
        await c.aclose()
        await svc.stop()
    assert peak[0] == 0


# -- security headers, Host allow-list ------------------------------------------------------------------------
def _csp(r) -> dict[str, list[str]]:
    out = {}
    for part in r.headers["content-security-policy"].split(";"):
        if part.strip():
            name, *values = part.split()
            out[name] = values
    return out


async def test_security_headers_on_every_response(service):
    c = service.client
    responses = [
        await c.get("/dashboard"),
        await c.get("/static/app.js"),
        await c.get(f"{API}/runs"),
        await c.get(f"{API}/runs/{'a' * 32}"),  # 404
        await c.post(f"{API}/runs", json={}),  # 401
        await c.get("/healthz"),
    ]
    for r in responses:
        assert r.headers["x-content-type-options"] == "nosniff", r.url
        assert r.headers["referrer-policy"] == "no-referrer"
        assert r.headers["x-frame-options"] == "DENY"
        csp = _csp(r)
        assert csp["frame-ancestors"] == ["'none'"] and csp["script-src"] == ["'self'"], r.url
        assert "'unsafe-inline'" not in csp["style-src"] and csp["object-src"] == ["'none'"]
    # the dashboard's page needs nothing from elsewhere, and no inline script or style
    html = responses[0].text
    refs = re.findall(r'(?:src|href)="([^"]*)"', html)
    assert refs and all(u == "#" or (u.startswith("/") and not u.startswith("//")) for u in refs), refs
    assert "<script>" not in html and "style=" not in html and "<style" not in html


async def test_docs_page_allowed_by_its_policy(service):
    """The interactive docs keep working: every script and stylesheet they load is allowed by their policy, and
    their inline start-up script too (scoped to the docs route)."""
    r = await service.client.get(f"{API}/docs")
    assert r.status_code == 200
    csp = _csp(r)
    assert r.headers["content-security-policy"] == CSP_DOCS
    assert csp["frame-ancestors"] == ["'none'"]
    for url in re.findall(r'(?:src|href)=["\']([^"\']+)["\']', r.text):
        if url.endswith((".js", ".css")):
            kind = "script-src" if url.endswith(".js") else "style-src"
            origin = "'self'" if url.startswith("/") and not url.startswith("//") else "/".join(url.split("/")[:3])
            assert origin in csp[kind], (url, csp[kind])
    if "<script>" in r.text:
        assert "'unsafe-inline'" in csp["script-src"]


async def test_host_allow_list(tmp_path, sim):
    svc = await start_service(make_settings(tmp_path, sim, allowed_hosts=["bench-7.lab.example"]), sim)
    c = svc.client
    try:
        assert (await c.get("/healthz", headers={"Host": "bench-7.lab.example"})).status_code == 200
        # the address the service binds (127.0.0.1 here) is always answered
        assert (await c.get("/healthz")).status_code == 200
        for bad in ("evil.example", "localhost.evil.example", "attacker"):
            r = await c.get("/healthz", headers={"Host": bad})
            assert r.status_code == 400 and r.headers["x-content-type-options"] == "nosniff", bad
        r = await c.post(f"{API}/runs", json={"plan": "line"}, headers={**AUTH, "Host": "evil.example"})
        assert r.status_code == 400 and svc.app.state.manager.bench_holder is None
    finally:
        await c.aclose()
        await svc.stop()


async def test_default_hosts_are_the_loopback_names(service):
    c = service.client
    port = service.url.rsplit(":", 1)[1]
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", "localhost"):
        assert (await c.get("/healthz", headers={"Host": host})).status_code == 200, host
    assert (await c.get("/healthz", headers={"Host": f"rebind.example:{port}"})).status_code == 400
