"""Run a Python example of the documentation as a user would, checking what its comments promise.

``python doc_python.py FILE [--stay]``: executes FILE statement by statement; an expression
statement whose line ends with a comment that is a Python literal (``list_robots(...)  # ['koch',
'so101']``) must evaluate to that literal, else the script exits 1 naming the line, the value and
the literal. ``--stay``: once every statement ran, print ``doc_python: ready`` and wait for SIGINT /
SIGTERM (an example that keeps something open, e.g. a Zenoh router), then exit 0.

Standard library only: it runs under the interpreter of whatever install is under test
(tests/doc_commands.py).
"""

from __future__ import annotations

import ast
import io
import signal
import sys
import tokenize


def literal_comments(source: str) -> dict[int, object]:
    """Line number -> the literal a trailing ``# <literal>`` comment on that line spells."""
    out = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type != tokenize.COMMENT:
            continue
        text = tok.string[1:].strip()
        try:
            out[tok.start[0]] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            pass  # prose, not a promised value
    return out


def main(argv: list[str]) -> int:
    path, stay = argv[0], "--stay" in argv[1:]
    source = open(path).read()
    tree = ast.parse(source, path)
    promised = literal_comments(source)
    scope: dict = {"__name__": "__main__"}
    for stmt in tree.body:
        if isinstance(stmt, ast.Expr) and stmt.end_lineno in promised:
            value = eval(compile(ast.Expression(stmt.value), path, "eval"), scope)  # noqa: S307 - the doc's own example
            want = promised[stmt.end_lineno]
            if value != want:
                print(f"{path}:{stmt.end_lineno}: {ast.get_source_segment(source, stmt)} gave {value!r}, "
                      f"the comment promises {want!r}", file=sys.stderr)
                return 1
        else:
            exec(compile(ast.Module([stmt], []), path, "exec"), scope)  # noqa: S102 - the doc's own example
    if stay:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: sys.exit(0))
        print("doc_python: ready", flush=True)
        while True:
            signal.pause()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
