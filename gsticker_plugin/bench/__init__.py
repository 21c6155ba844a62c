"""Benchmark commands: each measures and writes a docs page with its JSON beside it."""

from typing import List


def command_lines(title: str, when: str, json_name: str, command: str) -> List[str]:
    """A bench page's opening: its title, the command that wrote it (``when``: date and machine) and its JSON."""
    return [
        f"# {title}",
        "",
        f"Command ({when}; every number here is in [{json_name}]({json_name}), written by it):",
        "",
        "```bash",
        command,
        "```",
        "",
    ]
