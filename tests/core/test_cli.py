import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

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
    out = subprocess.run([sys.executable, "-m", "tacsplat"], capture_output=True, text=True)  # cli.run exits
    assert out.returncode == 2 and "usage: tacsplat" in out.stdout  # with main's code (no command: 2)


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2


def test_help_imports_no_heavy_package_and_python_m_works():
    code = (
        "import sys, runpy\nsys.argv = ['tacsplat', '--help']\n"
        "try:\n    runpy.run_module('tacsplat', run_name='__main__')\nexcept SystemExit:\n    pass\n"
        "print('HEAVY', sorted(m for m in ('torch', 'numba', 'mujoco', 'trimesh', 'scipy') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert "usage: tacsplat" in out.stdout and "HEAVY []" in out.stdout, out.stdout + out.stderr


def test_logging_options_are_accepted_before_and_after_the_subcommand(tmp_path, capsys):
    import logging

    for argv in (["-v", "inspect", str(tmp_path)], ["inspect", str(tmp_path), "-v"]):
        main(argv)
        assert logging.getLogger().level == logging.DEBUG
    main(["inspect", str(tmp_path), "--log-level", "warning"])
    assert logging.getLogger().level == logging.WARNING
    main(["inspect", str(tmp_path), "-q"])
    assert logging.getLogger().level == logging.WARNING
    main(["inspect", str(tmp_path)])
    assert logging.getLogger().level == logging.INFO


def test_debug_logging_shows_tacsplats_debug_lines_not_other_libraries(tmp_path, capsys):
    """-v (or --log-level DEBUG) is tacsplat's detail: PIL's or matplotlib's DEBUG lines (hundreds a command) would
    bury it; their INFO lines still show, as without -v."""
    import logging

    for option in (["-v"], ["--log-level", "debug"]):
        main(["inspect", str(tmp_path), *option])
        capsys.readouterr()
        logging.getLogger("tacsplat.datasets.scene").debug("ours")
        logging.getLogger("PIL.PngImagePlugin").debug("STREAM b'IHDR' 16 13")
        logging.getLogger("matplotlib").info("theirs at INFO")
        assert capsys.readouterr().err.splitlines() == [
            "DEBUG tacsplat.datasets.scene: ours",
            "INFO matplotlib: theirs at INFO",
        ], option


def test_exit_codes_usage_errors_are_2_runtime_errors_1(tmp_path, capsys):
    assert main(["bench", "paper", "--out", str(tmp_path / "b"), "--iterations", "many"]) == 2
    assert capsys.readouterr().err.startswith("tacsplat bench paper: error: --iterations: ")
    for value, why in (
        ("many", "--iterations: invalid literal for int() with base 10: 'many'"),
        ("-5", "--iterations: must be an integer >= 1, got -5"),
    ):  # (reconstruct's own parser)
        assert main(["reconstruct", str(tmp_path), "--out", str(tmp_path / "run"), "--iterations", value]) == 2
        err = capsys.readouterr().err
        assert err.strip() == f"tacsplat reconstruct: error: {why} (see tacsplat reconstruct --help)"
    for argv, why in (
        (["--out", str(tmp_path / "run")], "SCENE: required (the scene directory)"),
        ([str(tmp_path)], "--out: required"),
    ):
        assert main(["reconstruct", *argv]) == 2
        assert (
            capsys.readouterr().err.strip() == f"tacsplat reconstruct: error: {why} (see tacsplat reconstruct --help)"
        )
    assert main(["bench", "paper", "--out", str(tmp_path / "b"), "--seeds", "0,x"]) == 2
    assert main(["bench", "paper", "--out", str(tmp_path / "b"), "--methods", "3dgs,fancy"]) in (1, 2)
    assert "unknown method 'fancy'" in capsys.readouterr().err
    assert main(["reconstruct", str(tmp_path / "none"), "--out", str(tmp_path / "run")]) == 1  # no scene there
    capsys.readouterr()
    # a logging option before the command: the command still parses its own options and names itself
    assert main(["--log-level", "warning", "bench", "paper", "--out", str(tmp_path / "b"), "--iterations", "x"]) == 2
    assert capsys.readouterr().err.startswith("tacsplat bench paper: error: --iterations: ")


def test_required_options_are_marked_and_completion_is_printed(capsys):
    with __import__("pytest").raises(SystemExit) as stop:
        main(["sim-capture", "--help"])
    assert stop.value.code == 0
    help_text = " ".join(capsys.readouterr().out.split())
    assert "--resume) (required)" in help_text and "(0.025 to 0.3: the sizes the twin's hand grasps)" in help_text
    with pytest.raises(SystemExit):
        main(["--print-completion", "bash"])
    assert "complete" in capsys.readouterr().out


def test_the_completion_script_lists_each_commands_options_and_their_choices(capsys):
    """A command's options are parsed after argparse (by tyro, or by reconstruct itself): the completion script
    still lists them, not only -v, -q and --log-level."""
    with pytest.raises(SystemExit):
        main(["--print-completion", "bash"])
    script = capsys.readouterr().out
    options = {
        command: set(strings.split())
        for command, strings in re.findall(r"^_shtab_tacsplat_(\w+)_option_strings=\((.*)\)$", script, re.M)
    }
    assert {"--iterations", "--densify.max-gaussians", "--out", "--help", "--verbose"} <= options["reconstruct"]
    assert {"--object", "--out", "--grasps", "--no-resume"} <= options["sim_capture"]
    assert {"--all-pieces", "--voxel"} <= options["export_mesh"]
    assert "_shtab_tacsplat_reconstruct___method_choices=(3dgs 3dgs+s 3dgs+t paper default)" in script


def test_the_readmes_completion_line_installs_the_script_in_a_new_home(tmp_path):
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    line = " ".join(re.search(r"Shell completion[^`]*`([^`]*)`", readme)[1].split())
    bin_path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"  # (where tacsplat is installed)
    out = subprocess.run(["bash", "-c", line], env={**os.environ, "HOME": str(tmp_path), "PATH": bin_path})
    assert out.returncode == 0
    assert "--iterations" in (tmp_path / ".local/share/bash-completion/completions/tacsplat").read_text()


def test_an_option_whose_none_or_false_means_something_shows_that_as_its_one_default(capsys):
    """tyro adds "(default: None)" after a help that says what no value means: one default, the true one."""
    with pytest.raises(SystemExit):
        main(["export", "mesh", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "--out PATH mesh file, a .ply (default: RUN/mesh.ply) --voxel" in help_text
    assert "keep every connected piece (default: only the largest, the object) --overwrite" in help_text


def test_a_docstring_over_several_lines_shows_as_flowing_text_in_help(capsys, monkeypatch):
    """tyro kept a docstring's break before an indented line (a field docstring's second line) or one starting with
    no letter ("(use --host ..."): on a terminal wide enough, each text is one line of --help."""
    monkeypatch.setenv("COLUMNS", "1000")
    with pytest.raises(SystemExit):
        main(["view", "--help"])
    lines = capsys.readouterr().out.splitlines()
    for text in (
        "(the scene, without the side panel's controls), then exit (default: None)",  # ViewCommand.export
        "it prints the URL to open (use --host 0.0.0.0 or an SSH tunnel from another machine). --export writes",
    ):
        assert any(text in line for line in lines), "\n".join(lines)


def test_no_options_help_states_its_default_twice(capsys):
    """Every command's --help: an option whose help says its default (what its None or False means) gets no second
    one from tyro ("... (default 128) (default: None)")."""
    commands, stack = [], [((), build_parser())]
    while stack:
        words, parser = stack.pop()
        groups = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
        commands += [] if groups else [words]
        stack += [((*words, name), sub) for group in groups for name, sub in group.choices.items()]
    twice = []
    for words in sorted(commands):
        with pytest.raises(SystemExit):
            main([*words, "--help"])
        for entry in re.split(r"\n(?=  \S)", capsys.readouterr().out)[1:]:  # an argument's entry starts at column 2
            text = re.sub(r"\{[^}]*\}", "", " ".join(entry.split()))  # (without its choices: one may be "default")
            tyros = re.search(r"\(default: (None|False)\)$", text)
            if text.count("(default") > 1 or (tyros and "default" in text[: tyros.start()]):
                twice.append(f"tacsplat {' '.join(words)}: {text}")
    assert ("export", "mesh") in commands and not twice, "\n".join(twice)


def test_progress_is_plain_lines_without_a_terminal(capsys):
    from tacsplat.progress import progress_bar, set_quiet

    for _ in progress_bar(range(3), desc="copy", unit="frame"):
        pass
    err = capsys.readouterr().err
    assert err == "copy: 3/3 frame in 0 s\n" and "\r" not in err
    set_quiet(True)
    try:
        for _ in progress_bar(range(3), desc="copy"):
            pass
        assert capsys.readouterr().err == ""
    finally:
        set_quiet(False)


def test_an_output_on_a_read_only_or_full_disk_is_refused_before_any_work(tmpfs, capsys):
    """Every command's --out (and bench rasterizer's --json) is checked first: no benchmark or capture runs for
    minutes to fail at its first write."""
    read_only = tmpfs("64k", "ro")
    read_only.read_only()
    full = tmpfs("64k", "full")
    fd = os.open(full.path / "filler", os.O_WRONLY | os.O_CREAT)
    try:
        while os.write(fd, b"\0" * 4096):
            pass
    except OSError:
        pass  # full
    finally:
        os.close(fd)
    for command, option, path, reason in (
        (["bench", "rasterizer", "--json"], "--json", read_only.path / "r.json", "the file system is read-only"),
        (["demo", "--out"], "--out", read_only.path / "demo", "the file system is read-only"),
        (["sim-capture", "--out"], "--out", full.path / "scene", "the disk is full"),
    ):
        assert main([*command, str(path)]) == 1, command
        out, err = capsys.readouterr()
        assert err.splitlines() == [line for line in err.splitlines() if line.startswith(f"error: {option}: {path}")]
        assert len(err.splitlines()) == 1 and reason in err and out == "", (command, err, out)
        assert not path.exists()


def test_a_binary_file_given_as_a_yaml_file_is_one_error_naming_it(tmp_path, capsys):
    """A PNG passed as the rig, batch or settings file: one `error:` line naming the file, no traceback."""
    png = tmp_path / "photo.yaml"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    for argv in (
        ["rig", "check", "--rig", str(png)],
        ["batch", str(png), "--out", str(tmp_path / "b")],
        ["reconstruct", str(tmp_path), "--out", str(tmp_path / "r"), "--config", str(png)],
    ):
        assert main(argv) in (1, 2), argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and str(png) in err[0] and "UTF-8" in err[0], err


def test_an_output_on_a_pseudo_file_system_is_not_called_a_full_disk(tmp_path):
    """/proc reports no free blocks (and no blocks at all): a path there is not on a full disk."""
    from tacsplat.files import refuse_unwritable

    refuse_unwritable("--out", "/proc/no-such-folder/m.ply")  # (the command reports what it cannot reach)


def test_a_mistyped_option_is_named_with_the_nearest_one_wherever_it_stands(capsys):
    """tyro takes the word after an unknown option as its value: before a positional, it then said the positional
    was missing. The unknown option itself is the error, with the option it most likely meant."""
    for argv, typo, meant in (
        (["reconstruct", "--iteratons", "100", "SCENE", "--out", "RUN"], "--iteratons", "--iterations"),
        (["reconstruct", "SCENE", "--iteratons", "100", "--out", "RUN"], "--iteratons", "--iterations"),
        (["evaluate", "--gt-mseh", "x.ply", "RUN"], "--gt-mseh", "--gt-mesh"),
        (["view", "--prot=9000", "RUN"], "--prot", "--port"),
    ):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"error: {typo}: not an option of tacsplat {argv[0]} (did you mean {meant}?)" in err[0]


def test_a_word_of_an_options_help_is_not_taken_for_an_option(capsys):
    """Known options are the parser's, not every --word of --help (--ray-address's help quotes `ray start --head`)."""
    assert main(["bench", "paper", "--head"]) == 2
    assert "--head: not an option of tacsplat bench paper" in capsys.readouterr().err


def test_pyopengl_and_matplotlibs_font_cache_lines_are_hidden_at_info(tmp_path, capsys):
    """Their INFO lines (an optional speed-up missing; a font cache built in a new home) are noise between ours;
    their warnings still show."""
    import logging

    main(["inspect", str(tmp_path)])
    capsys.readouterr()
    logging.getLogger("OpenGL.acceleratesupport").info("No OpenGL_accelerate module loaded")
    logging.getLogger("matplotlib.font_manager").info("generated new fontManager")
    logging.getLogger("matplotlib.font_manager").warning("findfont: Font family not found")
    assert capsys.readouterr().err.splitlines() == ["WARNING matplotlib.font_manager: findfont: Font family not found"]
