"""Error messages checked by what they say, not how they say it: one line naming the file and the problem."""

from __future__ import annotations


def names(error, *tokens) -> str:
    """The message of ``error`` (an exception, pytest's ExceptionInfo, or a string), checked to be one line
    that contains each token: a file name, a field, a number. The wording around them is free."""
    message = str(getattr(error, "value", error))
    assert message.strip() and "\n" not in message.strip(), repr(message)
    missing = [str(token) for token in tokens if str(token) not in message]
    assert not missing, f"{message!r} does not name {missing}"
    return message
