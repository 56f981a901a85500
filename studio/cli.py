"""The `studio` command line: a table of subcommands, each implemented in the package that owns it.

Every entry names a module exposing ``add_arguments(parser)`` and ``run(args) -> int``. Modules are
imported only when their command runs, so ``studio --help`` stays instant and a heavy dependency
(torch, mujoco) is loaded only by the commands that need it.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "bench": ("studio.bench", "run a benchmark and print one JSON object"),
    "train": ("studio.model.train_command", "train OSVI-WM on recorded episodes (resumable, torchrun-ready)"),
    "train-decoder": ("studio.model.decoder_command", "train the latent image decoder of a trained model"),
    "pretrain-encoder": (
        "studio.model.pretrain_command",
        "self-supervised pretraining of the encoder on stored frames (a start for studio train --init)",
    ),
    "export-policy": (
        "studio.model.policy_export",
        "write a small inference file from a training checkpoint",
    ),
    "collect": ("studio.data.collect", "collect scripted expert/agent episodes in parallel (resumable)"),
    "import-video": ("studio.data.video_import", "store a human demonstration video as an expert episode"),
    "export-video": (
        "studio.data.video_export",
        "write a stored episode's frames as an MP4 (any size and frame rate, its timing kept)",
    ),
    "export": ("studio.data.export_command", "export episodes as a LeRobot v3.0 dataset"),
    "import": (
        "studio.data.import_command",
        "import trajectories or demonstration videos from a LeRobot v3.0 dataset",
    ),
    "serve": ("studio.ui.serve", "start the browser studio and print its URL"),
    "quickstart": (
        "studio.quickstart",
        "collect, train and evaluate a policy on this machine, timing each stage",
    ),
    "results": ("studio.eval.results", "held-out evaluations of one or more policies as a Markdown table"),
    "eval": ("studio.eval.evaluation", "imitation success on (unseen) tasks; every rollout stored"),
    "compare": (
        "studio.eval.compare",
        "two checkpoints on the same seeded scenes and demonstrations: a per-seed table of differences",
    ),
    "worker": ("studio.backend.worker", "run a sim or training worker that joins the studio's bus"),
    "hub": ("studio.backend.hub", "run the studio's bus, job queue and store without the browser UI"),
    "bus": (
        "studio.backend.credentials",
        "bus credentials: a CA, certificates, passwords and a Zenoh config per role (hub, sim, train, ui)",
    ),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="studio", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        sp.set_defaults(_module=module_name)
        # Arguments are added lazily below, only for the chosen command.
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0
    name = argv[0]
    if name not in COMMANDS:
        parser.error(f"unknown command {name!r}; choose from: {', '.join(COMMANDS)}")
    module = importlib.import_module(COMMANDS[name][0])
    sub = argparse.ArgumentParser(prog=f"studio {name}", description=COMMANDS[name][1])
    module.add_arguments(sub)
    args = sub.parse_args(argv[1:])
    return int(module.run(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
