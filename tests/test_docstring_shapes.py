"""Docstrings give array shapes in the letters of docs/architecture.md's "Dimension letters".

A public function or method (its name, its module's file name and its classes' names do not start
with `_`; functions nested in functions do not count) whose parameter or return annotations mention
`torch.Tensor`, `Tensor`, `np.ndarray`, `numpy.ndarray` or `ndarray` has a docstring that gives a
shape: a match of `SHAPE`, which is

- a parenthesised tuple (`TUPLE`: not right after a name or a closing bracket, so not `N(0, I)`)
  with at least one comma, whose items are dimensions: `...`, a number, a capital letter or name,
  or a product, sum or difference of them (`T`, `J_s`, `3J`, `3 V`, `T - 1`, `J * 4`), a lower-case
  name (`faces`, `n`), any of them starred (`*C`, `*shape`); and with an item that is not a
  lower-case name, or a trailing comma. So `(T, 22, 3)`, `(N,)`, `(n,)`, `(B, T, J, 3)`,
  `(..., 3, 3)`, `(*C, *S, 2)` and `(faces, 3)` count, and `(metres, radians)` and
  `(count, components)` do not (write the glossary's letters);
- or the words "scalar" (a loss), "same shape" ("the same shape as `x`") or "any shape(s)" (a
  function of tensors of every shape).

The source is read with `ast` (nothing is imported); humotion/live/web (the browser client and its
vendored three.js) is skipped.

The second test holds the letters to the glossary, which has no F: frames are T and a mesh's faces
are written out, (faces, 3). No docstring under humotion/ has a shape tuple with an F item, nor
writes faces (T, 3) or faces (F, 3).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "humotion"
SKIP = [PACKAGE / "live" / "web"]

ARRAY = re.compile(r"\b(?:torch\.Tensor|Tensor|np\.ndarray|numpy\.ndarray|ndarray)\b")

_TERM = r"(?:\d*\s?[A-Z]\w*|\d+)"
_DIM = rf"(?:\.\.\.|\*?{_TERM}(?:\s*[-+*/]\s*{_TERM})*|\*?[a-z_]+)"
TUPLE = re.compile(rf"(?<![\w)])\(\s*{_DIM}\s*,(?:\s*{_DIM}\s*,)*(?:\s*{_DIM})?\s*\)")
SHAPE = re.compile(rf"{TUPLE.pattern}|\bscalar\b|\bsame shape\b|\bany shapes?\b")
WORD = re.compile(r"[a-z_]+")


def gives_shape(docstring: str) -> bool:
    """Whether `docstring` has a shape: a `SHAPE` match that is not all lower-case words."""
    for match in SHAPE.finditer(docstring):
        text = match.group(0)
        if not text.startswith("("):
            return True
        items = [item.strip() for item in text[1:-1].split(",")]
        if items[-1] == "" or any(not WORD.fullmatch(item) for item in items):
            return True
    return False


def sources() -> list[Path]:
    """The Python files under humotion/ whose functions are checked."""
    return sorted(p for p in PACKAGE.rglob("*.py") if not any(s in p.parents for s in SKIP))


def public_module(path: Path) -> bool:
    """Whether no part of the path below humotion/ starts with `_` (a package's __init__.py aside)."""
    return all(not part.startswith("_") or part == "__init__.py" for part in path.relative_to(PACKAGE).parts)


def public_functions(tree: ast.Module):
    """(function, qualified name) for the module's public functions and its public classes' methods."""
    def walk(body, prefix: str):
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
                yield node, prefix + node.name
            elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                yield from walk(node.body, f"{prefix}{node.name}.")
    yield from walk(tree.body, "")


def takes_or_returns_array(function: ast.FunctionDef) -> bool:
    """Whether an annotation of a parameter or of the return mentions a tensor or an array."""
    args = function.args
    annotations = [a.annotation for a in args.posonlyargs + args.args + args.kwonlyargs] + [function.returns]
    annotations += [a.annotation for a in (args.vararg, args.kwarg) if a is not None]
    return any(a is not None and ARRAY.search(ast.unparse(a)) for a in annotations)


def offenders() -> list[str]:
    """`path:line name` of every public function taking or returning an array without a shape."""
    found = []
    for path in sources():
        if not public_module(path):
            continue
        tree = ast.parse(path.read_text(), str(path))
        for function, name in public_functions(tree):
            if takes_or_returns_array(function) and not gives_shape(ast.get_docstring(function) or ""):
                found.append(f"{path.relative_to(ROOT)}:{function.lineno} {name}")
    return found


def docstrings(tree: ast.Module):
    """(line, text) of every docstring in a module: the module's, its classes' and its functions'."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            text = ast.get_docstring(node, clean=False)
            if text is not None:
                yield node.body[0].lineno, text


FACES_AS_LETTER = re.compile(r"\bfaces\s*\(\s*[TF]\s*,")
"""faces (T, 3) or faces (F, 3): the glossary writes a mesh's faces (faces, 3)."""


def f_shapes() -> list[str]:
    """`path:line shape` of every docstring shape with an F item or faces given a letter."""
    found = []
    for path in sources():
        tree = ast.parse(path.read_text(), str(path))
        for line, text in docstrings(tree):
            matches = [m for m in TUPLE.finditer(text)
                       if any(re.search(r"(?<![\w.])F(?!\w)", item) for item in m.group(0)[1:-1].split(","))]
            matches += list(FACES_AS_LETTER.finditer(text))
            for match in sorted(matches, key=lambda m: m.start()):
                at = line + text[:match.start()].count("\n")
                found.append(f"{path.relative_to(ROOT)}:{at} {match.group(0)}")
    return found


def test_shape_pattern():
    for shaped in ["(T, 22, 3)", "(N,)", "(B, T, J, 3)", "(3, 3)", "(..., 4)", "(faces, 3)", "(T - 1, J * 4)",
                   "(H, W, 3) uint8", "a scalar tensor", "the same shape as `x`", "(T, 3J)", "(*C, *S, 2)",
                   "(n,)", "(3 V, hidden)", "values of any shape"]:
        assert gives_shape(shaped), shaped
    for unshaped in ["(metres)", "(metres, radians)", "(count, components)", "(see above)", "the shape parameters",
                     "(T)", "eps ~ N(0, I)", "(x0, y0, x1, y1)", ""]:
        assert not gives_shape(unshaped), unshaped


def test_public_array_functions_give_shapes():
    found = offenders()
    assert not found, (f"{len(found)} public functions take or return a tensor or array and give no shape "
                       "in their docstrings (see docs/architecture.md, Dimension letters):\n" + "\n".join(found))


def test_frames_are_T_and_faces_are_written_out():
    found = f_shapes()
    assert not found, ("docstrings with F in a shape (frames are T, faces are written (faces, 3); "
                       "docs/architecture.md, Dimension letters):\n" + "\n".join(found))
