"""Regular expressions from flags and files, in a linear-time engine (RE2): a pattern such as
(a+)+$ that keeps a backtracking engine busy for minutes on a long command line costs RE2 one
pass over it. RE2 has no backreferences and no lookaround: such a pattern is refused, with why.
RE2 is imported with the first pattern: an agent given none (most) does without its 1.5 MB."""
from __future__ import annotations


def compile(pattern: str):
    """The compiled pattern (its search() as re's); ValueError saying why RE2 refuses it."""
    import re2

    options = re2.Options()
    options.log_errors = False  # the reason goes into the one line the caller prints, not to stderr
    try:
        return re2.compile(pattern, options)
    except re2.error as e:
        why = e.args[0].decode(errors="replace") if e.args and isinstance(e.args[0], bytes) else str(e)
        raise ValueError(f"not a regular expression RE2 takes ({why})") from None
