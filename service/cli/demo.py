"""``i4cal demo``: the main job on the simulated bench, end to end."""

from __future__ import annotations

import argparse
import time


def handler(args: argparse.Namespace) -> int:

    from calib.observations import Observations
    from calib.pipeline import calibrate, to_jsonable
    from drivers.sim.twin import GeometricTwin

    from ._output import make_console, print_result

    con = make_console()
    t0 = time.perf_counter()
    con.rule("[bold]i4cal demo[/bold] - simulated I4 bench")
    twin = GeometricTwin()
    con.print("1. acquisition on the geometric twin: the paper's plan (rotation sweep, equal translation, "
              "20 fit poses, 4x5 locked-actuator poses, 500 mm line, validation poses)")
    obs = Observations.from_dict(twin.observations(seed=args.seed))
    con.print(f"   {len(obs.frames)} frames: " + ", ".join(f"{k} {v}" for k, v in obs.phases().items()))
    con.print("2. calibration with the three methods")
    doc = to_jsonable(calibrate(obs))
    print_result(doc, con)
    con.print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="simulate the bench and calibrate it with all methods",
                       description="The main job on the simulated bench: acquire, calibrate with the three "
                                   "methods, and print the comparison (the paper's Tables I-III).")
    p.add_argument("--seed", type=int, default=1)
    p.set_defaults(handler=handler)
