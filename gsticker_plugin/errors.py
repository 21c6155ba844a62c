"""One exception type for bad user input: commands print its one-line message and exit with status 2."""


class GStickerError(Exception):
    """A problem with the user's input; the message names the problem and the fix, on one line."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(message.split()))
