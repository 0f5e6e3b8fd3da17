#!/usr/bin/env python3
"""Fails when a function is over 120 lines or a file's non-test code is over 800 lines (issue 67).

Reads the Rust files git tracks, tests aside: files under a `tests/` folder, the end-to-end tests crate
(`tests/`), benchmarks, the fuzz targets, and each file's `#[cfg(test)] mod tests` (from there to the end of
the file, where the workspace keeps it). A function is counted from its `fn` line to its closing brace, found
by counting braces outside strings, characters and comments. No compilation.
"""
import re
import subprocess
import sys

MAX_FN = 120
MAX_FILE = 800
SKIP = re.compile(r"(^|/)(tests|benches)/|^fuzz/")
FN = re.compile(r'^\s*(pub(\([^)]*\))?\s+)?(const\s+)?(async\s+)?(unsafe\s+)?(extern\s+"C"\s+)?fn\s+(\w+)')
TESTS = re.compile(r"^\s*#\[cfg\(test\)\]\s*$")


def code_only(text):
    """The text with strings, characters and comments blanked (newlines kept), so braces can be counted."""
    out, i, n = [], 0, len(text)
    while i < n:
        c = text[i]
        if text.startswith("//", i):
            j = text.find("\n", i)
            j = n if j < 0 else j
            out.append(" " * (j - i))
            i = j
        elif text.startswith("/*", i):
            j = text.find("*/", i + 2)
            j = n if j < 0 else j + 2
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif (m := re.match(r'b?r(#*)"', text[i:])) is not None:
            end = '"' + m.group(1)
            j = text.find(end, i + len(m.group(0)))
            j = n if j < 0 else j + len(end)
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == '"':
            j = i + 1
            while j < n and text[j] != '"':
                j += 2 if text[j] == "\\" else 1
            j = min(j + 1, n)
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == "'" and (m := re.match(r"'(\\.|\\u\{[0-9a-fA-F]+\}|[^\\'])'", text[i:])) is not None:
            out.append(" " * len(m.group(0)))
            i += len(m.group(0))
        else:
            out.append(c)
            i += 1
    return "".join(out)


def check(path):
    text = open(path, encoding="utf-8").read()
    lines = code_only(text).split("\n")
    end = len(lines)
    for k, line in enumerate(lines):
        if TESTS.match(line) and k + 1 < len(lines) and re.match(r"\s*mod tests\b", lines[k + 1]):
            end = k
            break
    problems = []
    if end > MAX_FILE:
        problems.append(f"{path}: {end} lines of non-test code (at most {MAX_FILE}); split it by job")
    k = 0
    while k < end:
        m = FN.match(lines[k])
        if not m:
            k += 1
            continue
        depth, started, j = 0, False, k
        while j < end:
            depth += lines[j].count("{") - lines[j].count("}")
            started = started or "{" in lines[j]
            if started and depth <= 0:
                break
            if not started and lines[j].rstrip().endswith(";"):
                break
            j += 1
        if started and j - k + 1 > MAX_FN:
            problems.append(f"{path}:{k + 1}: fn {m.group(7)} is {j - k + 1} lines (at most {MAX_FN})")
        k = j + 1 if started else k + 1
    return problems


def main():
    files = subprocess.run(["git", "ls-files", "*.rs"], capture_output=True, text=True, check=True).stdout.split()
    files = [f for f in files if not SKIP.search(f)]
    problems = [p for f in files for p in check(f)]
    for p in problems:
        print(p, file=sys.stderr)
    if problems:
        return 1
    print(f"code-size: {len(files)} files, no function over {MAX_FN} lines, no file over {MAX_FILE} lines of non-test code")
    return 0


if __name__ == "__main__":
    sys.exit(main())
