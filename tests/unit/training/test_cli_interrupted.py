"""`n3dmap`'s one line on Ctrl-C: a plain KeyboardInterrupt prints "interrupted" and nothing of its own text (a
Ctrl-C that lands inside a codec comes back from CPython as KeyboardInterrupt("decoding with 'cp437' codec failed
(KeyboardInterrupt: )"), seen in `data generate`'s Ctrl-C test), while a TrainingInterrupted says where its
checkpoint is; both exit 130."""

import argparse

import pytest

import services.cli.main as cli
from services.training.loop import TrainingInterrupted


def _parser_raising(error: BaseException):
    def build_parser(argv=None, *, full=False):
        parser = argparse.ArgumentParser(prog="n3dmap")
        sub = parser.add_subparsers(dest="command", required=True)

        def func(args):
            raise error
        sub.add_parser("data").set_defaults(func=func)
        return parser
    return build_parser


@pytest.mark.parametrize("error, line", [
    (KeyboardInterrupt(), "n3dmap data: interrupted"),
    (KeyboardInterrupt("decoding with 'cp437' codec failed (KeyboardInterrupt: )"), "n3dmap data: interrupted"),
    (TrainingInterrupted("stopped by SIGINT after step 3 of 10; its checkpoint is saved in RUN"),
     "n3dmap data: interrupted: stopped by SIGINT after step 3 of 10; its checkpoint is saved in RUN"),
])
def test_ctrl_c_prints_one_line_and_exits_130(monkeypatch, capsys, error, line):
    monkeypatch.setattr(cli, "build_parser", _parser_raising(error))
    assert cli.main(["data"]) == 130
    assert capsys.readouterr().err.strip() == line
