#!/usr/bin/env python3
"""Fails when a Markdown document names a repository path that does not exist.

    scripts/doc-paths.py [FILE.md ...]        # default: ARCHITECTURE.md

What counts as a named path:
* every whitespace-separated word of an inline code span (`...`, outside fenced blocks) and every link target
  [text](target), once `:LINE`/`:LINE-LINE` suffixes, `#anchors` and surrounding punctuation are stripped;
* that consists only of path characters (letters, digits, `_ - . /`), so globs and placeholders (`*`, `{a,b}`,
  `<topic>`, `$VAR`, `a=b`) are not paths;
* and that ends in a known extension (EXTENSIONS), or ends in `/`, or contains a `/` after a first component
  that is a top-level entry of the repository (`.ci/run`, `deploy/k8s`). Other slashed words are not paths:
  `holoface-models/train` (a Cargo feature), `mouthRollUpper/Lower`.
Ignored: URLs (`scheme://`, `mailto:`), absolute paths, `~/...`, `../shared/...` (outside the checkout), module
paths (`a::b`), and generated or ignored locations: IGNORED_PREFIXES, anything starting with `.venv`, and every
anchored, glob-free entry of the root .gitignore (`runs/`, `target/`, `.cache/`, `.data/`, ...).
A code-span path is looked up from the repository root; a link target from the document's folder (as Markdown
resolves it) when the document is inside the repository, else from the root. It must exist as a file or a
folder; a path written with a trailing `/` must be a folder.
Prints `FILE:LINE: missing PATH` for each miss and exits 1 (2 when a file cannot be read); else prints one
count line and exits 0. Standard library only.
"""
import pathlib
import re
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
EXTENSIONS = {"rs", "py", "pyi", "sh", "md", "toml", "lock", "h", "c", "cs", "onnx", "bin", "txt", "json",
              "yml", "yaml", "pt", "service", "conf"}
IGNORED_PREFIXES = ("runs", "target", ".cache", ".data", "../shared")
PATH_CHARS = re.compile(r"^[A-Za-z0-9_./-]+$")
SPAN = re.compile(r"(`+)(.+?)\1", re.S)
LINK = re.compile(r"\]\(([^()\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.S | re.M)


def gitignored_prefixes():
    """Anchored, glob-free entries of the root .gitignore (`/target` -> `target`)."""
    try:
        lines = (ROOT / ".gitignore").read_text().splitlines()
    except OSError:
        return ()
    return tuple(line[1:].rstrip("/") for line in lines
                 if line.startswith("/") and not re.search(r"[*?\[]", line))


IGNORED = IGNORED_PREFIXES + gitignored_prefixes()


def candidate(word):
    """The path a word names, or None when it names none."""
    if "://" in word or word.startswith("mailto:") or "::" in word:
        return None
    word = word.lstrip("'\"([").rstrip("'\")]:,;.").split("#", 1)[0]
    word = re.sub(r":\d+(-\d+)?$", "", word).rstrip(":,;.")
    if not word or not PATH_CHARS.match(word) or word.startswith(("/", "~")) or word in (".", ".."):
        return None
    bare = word[2:] if word.startswith("./") else word
    last = bare.rstrip("/").rsplit("/", 1)[-1]
    has_ext = "." in last and last.rsplit(".", 1)[1] in EXTENSIONS
    top = bare.split("/", 1)[0]
    if "/" not in bare and not has_ext:
        return None
    if not has_ext and not bare.endswith("/") and not top.startswith(".") and not (ROOT / top).exists():
        return None  # `holoface-models/train` (a Cargo feature), `mouthRollUpper/Lower`: words, not paths
    if bare.startswith(".venv") or any(bare == p or bare.startswith(p + "/") for p in IGNORED):
        return None
    return word


def named_paths(text):
    """(line, path, from_link) for every path the text names, fenced code blocks left out."""
    text = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    for m in SPAN.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        for word in m.group(2).split():
            path = candidate(word)
            if path:
                yield line, path, False
    for m in LINK.finditer(SPAN.sub(lambda s: " " * len(s.group(0)), text)):
        path = candidate(m.group(1))
        if path:
            yield text.count("\n", 0, m.start()) + 1, path, True


def exists(path, base):
    target = base / path
    return target.is_dir() if path.endswith("/") else target.exists()


def main(args):
    files = [pathlib.Path(a) for a in args] or [ROOT / "ARCHITECTURE.md"]
    missing, checked = 0, set()
    for doc in files:
        try:
            text = doc.read_text(encoding="utf-8")
        except OSError as e:
            print(f"doc-paths: cannot read {doc}: {e.strerror}", file=sys.stderr)
            return 2
        for line, path, from_link in named_paths(text):
            base = doc.resolve().parent if from_link and doc.resolve().is_relative_to(ROOT) else ROOT
            checked.add((str(base), path))
            if not exists(path, base):
                print(f"{doc}:{line}: missing {path}")
                missing += 1
    if missing:
        print(f"doc-paths: {missing} missing path(s) named in {len(files)} file(s)")
        return 1
    print(f"doc-paths: {len(checked)} distinct repository paths named in {len(files)} file(s), all present")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
