"""``i4cal serve``: the REST service (FastAPI + uvicorn) and its dashboard."""

from __future__ import annotations

import argparse


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "serve",
        help="run the REST service and its dashboard",
        description=(
            "Serves /api/v1 (OpenAPI at /api/v1/docs) and the dashboard at /dashboard. Settings come from "
            "--config (TOML) and I4CAL_* environment variables; binds to 127.0.0.1 unless told otherwise."
        ),
    )
    p.add_argument("--config", "-c", default=None, help="service configuration (TOML), e.g. deploy/service-sim.toml")
    p.add_argument("--host", default=None, help="bind address (default from the settings: 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="port (default from the settings: 8000)")
    p.add_argument("--data-dir", default=None, help="data directory (database, datasets, results)")
    p.add_argument("--sim-bench", action="store_true", help="drive an in-process simulated bench")
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    import uvicorn

    from service.main import create_app
    from service.settings import load_settings

    over: dict = {}
    if args.host:
        over["host"] = args.host
    if args.port is not None:
        over["port"] = args.port
    if args.data_dir:
        over["data_dir"] = args.data_dir
    if args.sim_bench:
        over["sim_bench"] = True
    settings = load_settings(args.config, **over)
    app = create_app(settings)
    print(startup_lines(settings), flush=True)
    uvicorn.run(
        app,
        host=settings.host,
        port=settings.port,
        log_level=args.log_level,
        proxy_headers=False,
        timeout_graceful_shutdown=15,
    )
    return 0


def startup_lines(settings) -> str:
    """What ``serve`` says before it starts: the dashboard's and the API's addresses, the data directory."""
    host = settings.host
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else "[::1]" if host == "::" else host
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"
    port = settings.port if settings.port else "PORT (chosen at start: see the line below)"
    base = f"http://{shown}:{port}"
    listen = "" if shown == host else f" (listening on {host}: every interface)"
    return (
        f"i4cal dashboard: {base}/dashboard{listen}\n"
        f"REST API: {base}/api/v1 (OpenAPI: {base}/api/v1/docs)\n"
        f"data directory: {settings.data_dir.resolve()}"
    )
