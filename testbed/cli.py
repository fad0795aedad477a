"""The ``testbed`` command: ``run``, ``study``, ``generate``, ``render``.

Every sub-command takes a scene as a path to a TOML file or the name of one in ``scenes/``;
errors in the scene or the arguments are printed as one clear message (exit status 2),
never as a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from testbed.scene import SceneError, find_scene, load_scene


def _load(scene_arg):
    path = find_scene(scene_arg)
    return path, load_scene(path)


def cmd_run(args) -> int:
    from studies.main_job import run_main_job

    path, scene = _load(args.scene)
    result = run_main_job(scene, scene_path=path, seed=args.seed, out=args.out)
    if args.json:
        print(json.dumps(result, indent=2, default=float))
    else:
        from studies.main_job import format_result

        print(format_result(result))
    return 0


def cmd_study(args) -> int:
    from studies import available_studies, run_study

    if args.list or not args.name:
        for name, doc in available_studies().items():
            print(f"{name:16s} {doc}")
        return 0
    if args.out is None:
        raise SystemExit("testbed study: --out DIR is required")
    out = run_study(
        args.name, Path(args.out), scene=args.scene, seed=args.seed, quick=args.quick,
        workers=args.workers, scheduler=args.scheduler,
    )
    print(f"wrote {out / 'results.csv'} and {out / 'report.md'}")
    return 0


def cmd_render(args) -> int:
    from testbed.fluoroscope import render_command

    path, scene = _load(args.scene)
    render_command(scene, view=args.view, out=Path(args.out), seed=args.seed)
    print(f"wrote {args.out}")
    return 0


def cmd_generate(args) -> int:
    try:
        from testbed.generate import generate_command
    except ImportError:
        raise SystemExit("testbed generate: the dataset generator is not built yet "
                         "(the on-disk format is, in testbed/dataset.py)") from None

    path, scene = _load(args.scene)
    generate_command(scene, scene_path=path, cases=args.cases, out=Path(args.out), seed=args.seed)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="testbed",
        description="Simulation testbed for CT to X-ray registration for a surgical robot.",
    )
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="the main job on a scene (default scene if none)")
    r.add_argument("scene", nargs="?", default=None,
                   help="scene file or name (default: experiment2)")
    r.add_argument("--json", action="store_true", help="print one JSON object")
    r.add_argument("--seed", type=int, default=None, help="override the scene's seed")
    r.add_argument("--out", type=Path, default=None, help="folder for figures (optional)")
    r.set_defaults(func=cmd_run)

    s = sub.add_parser("study", help="run a study and write results.csv, report.md, figures")
    s.add_argument("name", nargs="?", help="study name (see --list)")
    s.add_argument("--out", type=Path, help="output folder")
    s.add_argument("--scene", default=None, help="scene file or name (study default if none)")
    s.add_argument("--seed", type=int, default=None, help="override the study's seed")
    s.add_argument("--quick", action="store_true", help="a small version (for smoke tests)")
    s.add_argument("--workers", type=int, default=1, help="worker processes")
    s.add_argument("--scheduler", default=None,
                   help="run trials on a Dask cluster: scheduler address tcp://HOST:PORT")
    s.add_argument("--list", action="store_true", help="list the studies")
    s.set_defaults(func=cmd_study)

    d = sub.add_parser("render", help="render one X-ray frame of a view to PNG")
    d.add_argument("scene", nargs="?", default=None)
    d.add_argument("--view", type=int, default=0, help="view index (0-based)")
    d.add_argument("--out", required=True)
    d.add_argument("--seed", type=int, default=None)
    d.set_defaults(func=cmd_render)

    g = sub.add_parser("generate", help="write a synthetic dataset")
    g.add_argument("scene", nargs="?", default=None)
    g.add_argument("--cases", type=int, default=1)
    g.add_argument("--out", required=True)
    g.add_argument("--seed", type=int, default=None)
    g.set_defaults(func=cmd_generate)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except SceneError as exc:
        print(f"testbed: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("testbed: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
