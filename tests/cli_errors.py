"""What a user's mistake on the command line must give: exit code 2 and one line."""

from hrp2_drake.cli import main


def refused(capsys, argv: list[str], *culprits: str) -> str:
    """Runs the command; asserts exit code 2 and ONE error line naming `culprits`, no
    traceback; returns the line."""
    code = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"hrp2-drake {argv[0]}: error: "), lines[0]
    for culprit in culprits:
        assert culprit in lines[0], lines[0]
    return lines[0]
