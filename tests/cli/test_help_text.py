"""Every option and positional of ``drivingscene`` (each command and ``bench <name>``) and of
``drivingscene-view`` says what it is in ``--help``."""

from __future__ import annotations

import argparse

import pytest

from drivingscene.cli import build_parser


def walk(parser: argparse.ArgumentParser, prog: str):
    """(command, action) for every argument of ``parser`` and of its subcommands, recursively."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from walk(sub, f"{prog} {name}")
        elif not isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            yield prog, action


def undocumented(parser: argparse.ArgumentParser, prog: str) -> list[str]:
    return [
        f"{command}: {'/'.join(action.option_strings) or action.dest}"
        for command, action in walk(parser, prog)
        if action.help is not argparse.SUPPRESS and not (action.help or "").strip()
    ]


def test_every_drivingscene_argument_has_help():
    parser = build_parser()
    commands = {command for command, _ in walk(parser, "drivingscene")}
    assert {"drivingscene bench raster", "drivingscene import ddad", "drivingscene export"} <= commands
    assert undocumented(parser, "drivingscene") == []


def test_every_viewer_argument_has_help():
    pytest.importorskip("drivingscene_view")
    from drivingscene_view.__main__ import build_parser as build_view_parser

    assert undocumented(build_view_parser(), "drivingscene-view") == []


def test_one_output_option_everywhere():
    """Commands that write one file or folder take it as ``-o/--out``."""
    parser = build_parser()
    outputs = {command: action for command, action in walk(parser, "drivingscene") if action.dest == "out"}
    for command in ("reconstruct", "oracle", "classical", "prune", "export", "synth", "train", "ship-weights", "import rig"):
        assert {"-o", "--out"} <= set(outputs[f"drivingscene {command}"].option_strings), command
    for command, action in outputs.items():
        assert {"-o", "--out"} <= set(action.option_strings), command
    args = parser.parse_args(["export", "r.npz", "--ply", "a.ply"])
    assert str(args.out) == "a.ply"


@pytest.mark.parametrize(
    "spaced, comma", [(["8x12", "16x24"], ["8x12,16x24"]), (["8x12", "16x24", "32x48"], ["8x12,16x24", "32x48"])]
)
def test_list_options_are_space_separated_and_accept_commas(spaced, comma):
    parser = build_parser()
    for bench in ("raster", "inference", "synth"):
        assert parser.parse_args(["bench", bench, "--sizes", *spaced]).sizes == spaced
        assert parser.parse_args(["bench", bench, "--sizes", *comma]).sizes == spaced
    args = parser.parse_args(["bench", "raster", "--max-layers", "4", "8", "--backends", "torch,cpp"])
    assert args.max_layers == [4, 8] and args.backends == ["torch", "cpp"]


def test_bad_list_item_is_one_line(capsys):
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["bench", "raster", "--max-layers", "4,x"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--max-layers" in err


def test_no_list_option_needs_its_flag_repeated():
    """Every list-valued option of ``drivingscene`` and ``drivingscene-view`` takes its values
    space-separated (repeating the flag still adds to the list); none only appends one per flag."""
    pytest.importorskip("drivingscene_view")
    from drivingscene_view.__main__ import build_parser as build_view_parser

    parsers = ((build_parser(), "drivingscene"), (build_view_parser(), "drivingscene-view"))
    repeat_only = [
        f"{command}: {'/'.join(action.option_strings)}"
        for parser, prog in parsers
        for command, action in walk(parser, prog)
        if isinstance(action, argparse._AppendAction) and action.nargs is None
    ]
    assert repeat_only == []
    view = build_view_parser().parse_args(["s.npz", "--time", "0", "0.25", "--time", "1", "--camera", "A", "B"])
    assert view.time == [0.0, 0.25, 1.0] and view.camera == ["A", "B"]
    bench = build_parser().parse_args(["bench", "choices", "--data", "d", "--variant", "", "match=off"])
    assert bench.variant == ["", "match=off"]


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_a_command_builds_its_own_parser_alone_and_the_same_one():
    """`drivingscene.cli.COMMANDS` names every command's module; the parser built for one command
    (start-up: the others' modules are not imported) parses its arguments as the whole parser does."""
    import importlib

    from drivingscene.cli import COMMAND_MODULES, COMMANDS
    from drivingscene.cli.bench import BENCHMARKS

    full = _commands(build_parser())
    assert set(COMMANDS) == set(full)
    for module in COMMAND_MODULES:  # each command is registered by the module the table names
        parser = argparse.ArgumentParser()
        importlib.import_module(f"drivingscene.cli.{module}").register(parser.add_subparsers())
        assert {c for c, m in COMMANDS.items() if m == module} == set(_commands(parser)), module
    alone = _commands(build_parser(["-v", "reconstruct", "scene.npz", "-o", "r.npz"]))
    assert set(alone) == {c for c, m in COMMANDS.items() if m == "recon"}
    argv = ["reconstruct", "scene.npz", "-o", "r.npz", "--budget", "0.4"]
    assert vars(build_parser(argv).parse_args(argv)).keys() == vars(build_parser().parse_args(argv)).keys()
    assert build_parser(argv).parse_args(argv).budget == build_parser().parse_args(argv).budget == 0.4
    benchmarks = _commands(_commands(build_parser(["bench", "inference", "--runs", "1"]))["bench"])
    assert set(benchmarks) == {"inference"}
    assert set(_commands(_commands(build_parser(["bench", "nope"]))["bench"])) == set(BENCHMARKS)  # the error lists them all
    assert set(_commands(build_parser(["nope"]))) == set(full)
