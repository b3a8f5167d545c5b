"""Lines of code of the package: every `.py` file outside tests/ and hidden folders, counting the lines that hold a
token that is not a comment, leaving out blank lines and docstrings: module, class and function ones, and PEP 257's
attribute docstrings (a string right after an assignment in a module or class body: the field help tyro reads).

    python3 .ci/loc.py [ROOT]      # ROOT: a checkout (default: this one); prints the total, then per top folder
"""

import ast
import io
import sys
import tokenize
from pathlib import Path

SKIPPED = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER}


def is_string(statement: ast.stmt) -> bool:
    return (
        isinstance(statement, ast.Expr)
        and isinstance(statement.value, ast.Constant)
        and isinstance(statement.value.value, str)
    )


def lines_of_code(source: str) -> int:
    docstrings = set()
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) or not node.body:
            continue
        strings = [node.body[0]] if is_string(node.body[0]) else []
        if isinstance(node, (ast.Module, ast.ClassDef)):
            pairs = zip(node.body, node.body[1:])
            strings += [s for prev, s in pairs if is_string(s) and isinstance(prev, (ast.Assign, ast.AnnAssign))]
        for string in strings:
            docstrings.update(range(string.lineno, string.end_lineno + 1))
    code = set()
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type not in SKIPPED:
            code.update(range(token.start[0], token.end[0] + 1))
    return len(code - docstrings)


def main(root: Path) -> None:
    per_folder: dict[str, int] = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root).parts
        if "tests" in parts or any(part.startswith(".") for part in parts):
            continue
        per_folder[parts[0]] = per_folder.get(parts[0], 0) + lines_of_code(path.read_text())
    print(sum(per_folder.values()), per_folder)


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1])
