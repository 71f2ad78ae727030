"""A throwaway PostgreSQL cluster for the tests: ``initdb`` + ``pg_ctl`` on a unix socket in a temporary directory.

The server binaries come from Debian's ``postgresql`` package (deploy/install-test-system-deps.sh). ``initdb``
refuses to run as root: as root, the cluster belongs to the ``postgres`` account the package creates (commands run
through ``runuser``); otherwise to the current user. Nothing listens on TCP (``listen_addresses = ''``).
"""

from __future__ import annotations

import contextlib
import os
import pwd
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path


class ClusterUnavailableError(Exception):
    """Why no cluster can be started here (the test is skipped with this reason)."""


def server_bindir() -> Path:
    """The directory of ``initdb``/``pg_ctl``/``postgres`` (newest installed major version)."""
    cands = sorted(
        Path("/usr/lib/postgresql").glob("*/bin"),
        key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0,
        reverse=True,
    )
    for d in cands:
        if (d / "initdb").is_file() and (d / "pg_ctl").is_file():
            return d
    initdb = shutil.which("initdb")
    if initdb and shutil.which("pg_ctl"):
        return Path(initdb).resolve().parent
    raise ClusterUnavailableError(
        "no PostgreSQL server binaries (initdb, pg_ctl): run deploy/install-test-system-deps.sh"
    )


def _runner() -> tuple[list[str], str | None]:
    """The command prefix to run the server as a non-root user, and that user (None: the current one)."""
    if os.geteuid() != 0:
        return [], None
    try:
        pwd.getpwnam("postgres")
    except KeyError:
        raise ClusterUnavailableError(
            "running as root and there is no 'postgres' account to own the cluster (initdb refuses root)"
        ) from None
    runuser = shutil.which("runuser")
    if runuser is None:
        raise ClusterUnavailableError("running as root without runuser to start the cluster as 'postgres'")
    return [runuser, "-u", "postgres", "--"], "postgres"


@contextlib.contextmanager
def temporary_cluster(database: str = "i4cal") -> Iterator[str]:
    """Start a cluster, create ``database``, yield its SQLAlchemy URL (psycopg 3, unix socket); stop and delete it.

    Raises
    ------
    ClusterUnavailableError
        No server binaries, no non-root account to run them, or the server does not start (the log is quoted).
    """
    bindir = server_bindir()
    prefix, user = _runner()
    root = Path(tempfile.mkdtemp(prefix="i4cal-pg-"))
    data, sock, log = root / "data", root / "sock", root / "server.log"
    sock.mkdir()
    if user is not None:
        pw = pwd.getpwnam(user)
        for p in (root, sock):
            os.chown(p, pw.pw_uid, pw.pw_gid)
    started = False
    try:
        r = subprocess.run(
            [
                *prefix,
                str(bindir / "initdb"),
                "-D",
                str(data),
                "-U",
                "i4cal",
                "--auth=trust",
                "-E",
                "UTF8",
                "--locale=C",
                "--no-sync",
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
        if r.returncode != 0:
            raise ClusterUnavailableError(f"initdb failed: {r.stderr.strip()[-500:]}")
        opts = f"-k {sock} -c listen_addresses='' -p 5432 -c fsync=off -c synchronous_commit=off"
        r = subprocess.run(
            [*prefix, str(bindir / "pg_ctl"), "-D", str(data), "-l", str(log), "-w", "-t", "60", "-o", opts, "start"],
            capture_output=True,
            text=True,
            timeout=90,
        )
        if r.returncode != 0:
            tail = log.read_text(errors="replace")[-800:] if log.exists() else r.stderr
            raise ClusterUnavailableError(f"pg_ctl start failed: {tail.strip()}")
        started = True
        import psycopg

        with psycopg.connect(host=str(sock), port=5432, user="i4cal", dbname="postgres", autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{database}"')
        yield f"postgresql+psycopg://i4cal@/{database}?host={sock}&port=5432"
    finally:
        if started:
            subprocess.run(
                [*prefix, str(bindir / "pg_ctl"), "-D", str(data), "-m", "immediate", "-w", "stop"],
                capture_output=True,
                timeout=60,
            )
        shutil.rmtree(root, ignore_errors=True)
