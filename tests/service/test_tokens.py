"""Bearer tokens: ``i4cal token create [--expires-in|--expires-at]``, ``list``, ``revoke``; an
expired or revoked token gets 401, ``token_hashes`` of the configuration keep working. The command line runs in this
process (``service.cli.main``) on the service's data directory; the service is real (uvicorn on loopback)."""

from __future__ import annotations

import asyncio
import json
from datetime import UTC, datetime, timedelta

import pytest

from service.auth import create_token_record, hash_token
from service.cli import main as cli
from service.cli.token import parse_duration
from service.db import Database
from tests.service.conftest import TOKEN, make_settings, start_service

API = "/api/v1"
NO_RUN = f"{API}/runs/{'0' * 32}/abort"  # a POST that needs a token: 404 once the token is accepted, 401 before


def _run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = cli(["token", *argv])
    out, err = capsys.readouterr()
    return code, out, err


def _list(capsys, data_dir) -> list[dict]:
    code, out, _ = _run_cli(capsys, "list", "--data-dir", str(data_dir), "--json")
    assert code == 0
    return json.loads(out)


def test_durations():
    assert parse_duration("30d") == timedelta(days=30)
    assert parse_duration("1d12h") == timedelta(hours=36)
    assert parse_duration("90m") == timedelta(minutes=90)
    for bad in ("", "30", "soon", "0s", "-3d", "3d soon"):
        with pytest.raises(Exception, match="duration"):
            parse_duration(bad)


async def test_create_list_revoke_expire(tmp_path, sim, capsys):
    data = tmp_path / "data"
    code, out, err = _run_cli(capsys, "create", "--data-dir", str(data), "--name", "robot cell 3")
    assert code == 0 and "shown only now" in err
    t1 = out.strip()
    code, out, err = _run_cli(capsys, "create", "--data-dir", str(data), "--name", "visitor", "--expires-in", "30d")
    t2 = out.strip()
    assert code == 0 and "expires" in err
    # an expiry in the past is refused, one line, status 2
    code, _, err = _run_cli(capsys, "create", "--data-dir", str(data), "--expires-at", "2020-01-01T00:00Z")
    assert code == 2 and "in the past" in err and "--expires-at" in err

    rows = _list(capsys, data)
    assert [r["name"] for r in rows] == ["robot cell 3", "visitor"]
    assert all(r["state"] == "active" and r["last_used"] is None and r["created"].endswith("Z") for r in rows)
    exp = datetime.fromisoformat(rows[1]["expires"])
    assert abs(exp - (datetime.now(UTC) + timedelta(days=30))) < timedelta(minutes=5) and rows[0]["expires"] is None
    assert rows[0]["prefix"] == t1[:8] + "…"
    # never the token nor its hash, in either form of the list
    code, table, _ = _run_cli(capsys, "list", "--data-dir", str(data))
    for t in (t1, t2):
        for text in (json.dumps(rows), table):
            assert t not in text and hash_token(t) not in text and t[8:16] not in text
    assert "robot cell 3" in table and "visitor" in table

    # a token about to expire, stored the way `create --expires-at` stores it
    db = Database(f"sqlite:///{(data / 'i4cal.db').resolve()}")
    try:
        t3, _ = create_token_record(db, "short", datetime.now(UTC) + timedelta(seconds=1.5))
    finally:
        db.dispose()

    svc = await start_service(make_settings(tmp_path, sim), sim)  # token_hashes holds TOKEN
    c = svc.client
    try:
        for t in (t1, t2, t3, TOKEN):
            r = await c.post(NO_RUN, headers={"Authorization": f"Bearer {t}"})
            assert r.status_code == 404, (t[:8], r.text)
        by_name = {r["name"]: r for r in _list(capsys, data)}
        assert by_name["robot cell 3"]["last_used"] is not None and by_name["robot cell 3"]["last_used"].endswith("Z")

        code, _, err = _run_cli(capsys, "revoke", "--data-dir", str(data), str(by_name["robot cell 3"]["id"]))
        assert code == 0 and "revoked" in err
        r = await c.post(NO_RUN, headers={"Authorization": f"Bearer {t1}"})
        assert r.status_code == 401 and r.json()["detail"] == "token revoked"
        assert r.headers["www-authenticate"] == "Bearer"
        # the others still work, the configured token_hashes too
        assert (await c.post(NO_RUN, headers={"Authorization": f"Bearer {t2}"})).status_code == 404
        assert (await c.post(NO_RUN, headers={"Authorization": f"Bearer {TOKEN}"})).status_code == 404

        await asyncio.sleep(1.6)
        r = await c.post(NO_RUN, headers={"Authorization": f"Bearer {t3}"})
        assert r.status_code == 401 and r.json()["detail"] == "token expired"
        states = {r["name"]: r["state"] for r in _list(capsys, data)}
        assert states == {"robot cell 3": "revoked", "visitor": "active", "short": "expired"}
    finally:
        await c.aclose()
        await svc.stop()

    code, _, err = _run_cli(capsys, "revoke", "--data-dir", str(data), "999")
    assert code == 2 and "no stored token has id 999" in err


async def test_revoked_token_refused_on_closed_reads(tmp_path, sim):
    svc = await start_service(make_settings(tmp_path, sim, open_reads=False), sim)
    c = svc.client
    try:
        token, tid = create_token_record(svc.app.state.db, "reader")
        h = {"Authorization": f"Bearer {token}"}
        assert (await c.get(f"{API}/runs", headers=h)).status_code == 200
        assert cli(["token", "revoke", "--data-dir", str(svc.settings.data_dir), str(tid)]) == 0
        assert (await c.get(f"{API}/runs", headers=h)).status_code == 401
    finally:
        await c.aclose()
        await svc.stop()


def test_hash_only_takes_no_expiry(capsys):
    code, out, err = _run_cli(capsys, "create", "--hash-only")
    assert code == 0 and err.startswith("token_hashes = [") and hash_token(out.strip()) in err
    code, _, err = _run_cli(capsys, "create", "--hash-only", "--expires-in", "1d")
    assert code == 2 and "do not expire" in err
