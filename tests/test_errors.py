"""The one runner every gsticker command goes through: a failure is one ``error:`` line and exit status 2."""

import pytest

from gsticker_plugin.errors import EXIT_ERROR, GStickerError, run_command


def _raise(exc):
    def body():
        raise exc

    return body


def test_bad_input_and_unreadable_paths_are_one_error_line_with_exit_2(capsys):
    assert run_command(_raise(GStickerError("the key is missing;\n  pass --key"))) == EXIT_ERROR
    assert capsys.readouterr().err == "error: the key is missing; pass --key\n"
    assert run_command(_raise(FileNotFoundError(2, "No such file or directory", "x.yml"))) == EXIT_ERROR
    assert capsys.readouterr().err.startswith("error: No such file or directory (x.yml);")


def test_a_crash_is_one_line_naming_what_it_means_only_when_the_command_says_so(capsys):
    assert run_command(_raise(ValueError("bad\nshape")), crash="no verdict") == EXIT_ERROR
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: no verdict: ValueError: bad shape at test_errors.py:")
    with pytest.raises(ValueError):  # without ``crash`` a bug keeps its traceback
        run_command(_raise(ValueError("bug")))


def test_the_body_s_status_is_the_command_s():
    assert run_command(lambda: 1) == 1 and run_command(lambda: 0, crash="no verdict") == 0
