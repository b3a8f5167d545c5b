import subprocess
import sys

from tacsplat.cli import build_parser, main


def test_help_lists_commands_and_every_command_has_help(capsys):
    parser = build_parser()
    text = parser.format_help()
    assert "demo" in text
    # every registered (sub)command has a non-empty description
    stack = [parser]
    while stack:
        p = stack.pop()
        for action in p._actions:
            if action.__class__.__name__ == "_SubParsersAction":
                for name, sub in action.choices.items():
                    assert sub.description, f"`{sub.prog}` has no description"
                    stack.append(sub)


def test_console_script_runs():
    out = subprocess.run([sys.executable, "-m", "tacsplat.cli", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and "tacsplat" in out.stdout


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
