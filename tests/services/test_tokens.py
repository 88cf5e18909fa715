"""Tokens: the generator never makes one that starts with "-", and every command that takes a token takes any token,
an older server's "-..." ones too, as ``--token=T``, ``--token T`` and ``--token-file PATH`` (issue 19, item 4).

A fresh clone's test run failed on ``unwind jobs list --token -rluO...`` (argparse: "expected one argument"):
``secrets.token_urlsafe(32)`` starts with "-" once in 64 draws.
"""

from __future__ import annotations

import argparse
import base64
import os
import string
import subprocess
import sys

import pytest
from _servers import ROOT, ServerProcess

from napari_unwind import cli
from napari_unwind._cliargs import join_dash_values
from napari_unwind._tokenfile import read_token_file
from napari_unwind.errors import InvalidInputError
from unwind_services.auth import TokenAuth, add_token, hash_token, new_token

N_TOKENS = 1000
N_STORED = 100  # of them made by add_token (each rewrites the tokens file), the rest by new_token
URLSAFE = set(string.ascii_letters + string.digits + "-_")

#: Tokens an older server issued (``token_urlsafe(32)``: 43 characters, any of them "-" or "_") or a person typed:
#: each would be read as an option by plain argparse after ``--token``.
OLD_STYLE = [
    "-rluO" + "x" * 38,                                  # the token of the failing run, padded to 43 characters
    "--" + "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNO",  # two dashes: looks like a long option
    "-q" + "_" * 41,                                     # starts like the short option -q of the same commands
    "-" * 43,
    "-_-" + "0123456789" * 4,
    "-h" + "9" * 41,                                     # starts like -h (help)
    "-1",                                                # looks like a negative number
]


@pytest.fixture(scope="module")
def tokens_file(tmp_path_factory):
    """N_TOKENS tokens of the server's own generator, the first N_STORED made by add_token into a tokens file."""
    path = tmp_path_factory.mktemp("tokens") / "tokens"
    made = [add_token(path, f"user{i % 7}") for i in range(N_STORED)]
    return path, made + [new_token() for _ in range(N_TOKENS - N_STORED)]


def test_the_generator_never_starts_a_token_with_a_dash(tokens_file):
    path, made = tokens_file
    made = made + [new_token() for _ in range(N_TOKENS)]  # 2000 in all
    assert len(set(made)) == len(made)
    for token in made:
        assert not token.startswith("-"), token
        assert token[0] in string.ascii_letters + string.digits, token  # nothing a shell or argparse misreads
        assert set(token) <= URLSAFE and len(token) == 44, token
        # the 43 characters after the first are token_urlsafe(32): all 32 random bytes are there (entropy kept)
        assert len(base64.urlsafe_b64decode(token[1:] + "=")) == 32
    # the first character is drawn from all 62 letters and digits, not a fixed one (2000 draws miss none of
    # them with probability 62 * (61/62)**2000 ~ 4e-13)
    assert {t[0] for t in made} == set(string.ascii_letters + string.digits)
    # what add_token stored is each token's hash, and each token is its user's
    auth = TokenAuth(path)
    text = path.read_text()
    for i, token in enumerate(made[:N_STORED]):
        assert token not in text and hash_token(token) in text
        assert auth.user_for(f"Bearer {token}") == f"user{i % 7}"


def test_tokens_an_older_server_issued_still_authenticate(tmp_path):
    """The tokens file holds hashes: a "-..." token in an existing file is still its user's."""
    path = tmp_path / "tokens"
    path.write_text("".join(f"old{i} {hash_token(t)}\n" for i, t in enumerate(OLD_STYLE)))
    auth = TokenAuth(path)
    for i, token in enumerate(OLD_STYLE):
        assert auth.user_for(f"Bearer {token}") == f"old{i}"


# ------------------------------------------------------------------------------------------------------------------
# every command that takes a token, found in the parser
# ------------------------------------------------------------------------------------------------------------------
def _commands_with_token(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                if any("--token" in a.option_strings for a in sub._actions):
                    found[name] = sub
    return found


def _value(action: argparse.Action) -> str:
    return str(next(iter(action.choices))) if action.choices else "x"


def _minimal_argv(name: str, sub: argparse.ArgumentParser) -> list[str]:
    """The command and what it cannot do without: its required positionals and required options."""
    argv = [name]
    for action in sub._actions:
        if action.option_strings:
            if action.required:
                argv += [action.option_strings[-1], _value(action)]
        elif action.nargs not in ("?", "*", argparse.SUPPRESS):
            argv.append(_value(action))
    return argv


PARSER = cli.build_parser()
COMMANDS = _commands_with_token(PARSER)


def test_the_commands_with_a_token_are_found():
    # the enumeration finds at least the ones known today (a new one is picked up by the loop below)
    assert {"run", "submit", "jobs"} <= set(COMMANDS)
    assert all(any("--token-file" in a.option_strings for a in sub._actions) for sub in COMMANDS.values())


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_takes_every_token_in_every_form(name, tokens_file, tmp_path):
    base = _minimal_argv(name, COMMANDS[name])
    assert PARSER.parse_args(base).token is None  # the minimal command parses as it is
    token_file = tmp_path / "token"
    _, made = tokens_file
    for i, token in enumerate(made + OLD_STYLE):
        token_file.write_text(token + "\n")
        forms = [["--token=" + token], ["--token", token], ["--token-file", str(token_file)]]
        for form in forms:
            # after the command's own arguments, and right after the command's name
            for argv in (base + form, base[:1] + form + base[1:]):
                args = PARSER.parse_args(argv)
                assert args.token == token, (argv, args.token)
                assert args.func is COMMANDS[name].get_default("func")
        if i % 100 == 0:  # the other options still parse around it
            args = PARSER.parse_args(base + ["--token", token, "--server", "h:1", "--tls"])
            assert (args.token, args.server, args.tls) == (token, "h:1", True)


def test_a_token_file_is_read_whole_and_a_bad_one_is_one_line(tmp_path, capsys):
    good = tmp_path / "good"
    good.write_text("  -abc_DEF-123  \r\n\n")
    assert read_token_file(good) == "-abc_DEF-123"
    missing, empty, folder, many = tmp_path / "missing", tmp_path / "empty", tmp_path / "folder", tmp_path / "many"
    empty.write_text("\n \n")
    folder.mkdir()
    many.write_text("token for alice (shown once; its hash is in tokens):\nabc\n")
    cases = [(missing, "does not exist"), (empty, "is empty"), (folder, "is a folder"), (many, "more than one")]
    if os.geteuid() != 0:  # root reads any file
        locked = tmp_path / "locked"
        locked.write_text("abc\n")
        locked.chmod(0)
        cases.append((locked, "permission denied"))
    for path, words in cases:
        with pytest.raises(InvalidInputError, match=words):
            read_token_file(path)
        for name in sorted(COMMANDS):
            capsys.readouterr()
            assert cli.main(_minimal_argv(name, COMMANDS[name]) + ["--token-file", str(path)]) == 1
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].startswith("unwind: error: argument --token-file: "), err
            assert words in err[0] and "--token=VALUE" in err[0] and str(path) in err[0], err


def test_a_forgotten_token_is_still_an_error(capsys):
    name = sorted(COMMANDS)[0]
    base = _minimal_argv(name, COMMANDS[name])
    for argv in (base + ["--token"], base + ["--token", "--server", "h:1"], base + ["--token", "-q"],
                 base + ["--token", "x", "--token-file", "f"]):
        capsys.readouterr()
        assert cli.main(argv) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "argument --token" in err[0], err
    # nothing after "--" is joined
    assert join_dash_values(["a", "--", "--token", "-x"], set()) == ["a", "--", "--token", "-x"]
    assert join_dash_values(["--token", "-x", "--q"], {"--q"}) == ["--token=-x", "--q"]


def test_the_client_reads_unwind_token_file(tmp_path, monkeypatch):
    from napari_unwind.client import Client

    path = tmp_path / "token"
    path.write_text(OLD_STYLE[0] + "\n")
    monkeypatch.delenv("UNWIND_TOKEN", raising=False)
    monkeypatch.setenv("UNWIND_TOKEN_FILE", str(path))
    with Client("127.0.0.1:9", progress=False) as c:
        assert c._metadata == (("authorization", f"Bearer {OLD_STYLE[0]}"),)
    monkeypatch.setenv("UNWIND_TOKEN", "from-env")  # $UNWIND_TOKEN first, the argument before both
    with Client("127.0.0.1:9", progress=False) as c:
        assert c._metadata == (("authorization", "Bearer from-env"),)
    with Client("127.0.0.1:9", token="given", progress=False) as c:
        assert c._metadata == (("authorization", "Bearer given"),)
    monkeypatch.delenv("UNWIND_TOKEN")
    monkeypatch.setenv("UNWIND_TOKEN_FILE", str(tmp_path / "missing"))
    with pytest.raises(InvalidInputError, match="does not exist"):
        Client("127.0.0.1:9", progress=False)


# ------------------------------------------------------------------------------------------------------------------
# end to end: a real server, a token that starts with "-"
# ------------------------------------------------------------------------------------------------------------------
def test_jobs_list_with_a_dash_token_against_a_real_server(tmp_path, capsys):
    old = "-rluO" + "Ab3_-" * 7 + "xyz"  # as an older server issued it: 43 characters, first "-"
    tokens = tmp_path / "tokens"
    tokens.write_text(f"olduser {hash_token(old)}\n")
    new = add_token(tokens, "newuser")
    srv = ServerProcess(tmp_path / "data", "--tokens", tokens, "--workers", "1")
    try:
        env = {**os.environ, "UNWIND_TOKEN": "", "UNWIND_TOKEN_FILE": ""}
        out = subprocess.run([sys.executable, "-m", "napari_unwind.cli", "jobs", "list", "--server", srv.address,
                              f"--token={old}"], capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
        assert out.returncode == 0, out.stderr
        token_file = tmp_path / "old.token"
        token_file.write_text(old + "\n")
        for form in (["--token", old], ["--token-file", str(token_file)], ["--token", new]):
            capsys.readouterr()
            assert cli.main(["jobs", "list", "--server", srv.address, *form]) == 0, capsys.readouterr().err
        # the server checked that very token: without its "-", or another "-" token, it is unknown
        for wrong in (old[1:], "-" + old[2:], "-" + new):
            capsys.readouterr()
            assert cli.main(["jobs", "list", "--server", srv.address, f"--token={wrong}"]) == 1
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and "unknown token" in err[0], err
    finally:
        srv.stop()


# ------------------------------------------------------------------------------------------------------------------
# a typo in the tokens file (issue 22 item 5)
# ------------------------------------------------------------------------------------------------------------------
def test_a_typo_in_the_tokens_file_keeps_the_last_good_table_and_tells_only_the_log(tmp_path):
    from napari_unwind.client import Client, RemoteError

    tokens = tmp_path / "tokens"
    alice = add_token(tokens, "alice")
    srv = ServerProcess(tmp_path / "data", "--tokens", tokens, "--workers", "1")
    try:
        with Client(srv.address, token=alice, progress=False) as c:
            c.volumes()
        good = tokens.read_text()
        bob = new_token()
        # an admin's typo: bob's hash one digit short, on line 3 of the file
        typo = f"bob {hash_token(bob)[:-1]}"
        tokens.write_text(good + typo + "\n")
        os.utime(tokens, ns=(os.stat(tokens).st_atime_ns, os.stat(tokens).st_mtime_ns + 10**9))  # a new mtime
        for _ in range(3):
            with Client(srv.address, token=alice, progress=False) as c:  # the last good table still holds alice
                c.volumes()
        for wrong in (bob, "not-a-token"):
            with Client(srv.address, token=wrong, progress=False) as c, pytest.raises(RemoteError) as err:
                c.volumes()
            message = str(err.value)
            assert err.value.code == "UNAUTHENTICATED", (err.value.code, message)
            assert str(tmp_path) not in message and "tokens" not in message.replace("token;", "") \
                and "sha256" not in message and "line" not in message, message
        log = srv.log.read_text()
        said = [line for line in log.splitlines() if "tokens file not reloaded" in line]
        assert len(said) == 1, said  # once, not at every call
        assert str(tokens) in said[0] and "line 3" in said[0], said[0]
        # the admin fixes the line: bob's token works without a restart
        tokens.write_text(good + f"bob {hash_token(bob)}\n")
        os.utime(tokens, ns=(os.stat(tokens).st_atime_ns, os.stat(tokens).st_mtime_ns + 2 * 10**9))
        with Client(srv.address, token=bob, progress=False) as c:
            c.volumes()
    finally:
        srv.stop()
