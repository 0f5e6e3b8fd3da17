#!/usr/bin/env python3
"""The facade's rustdoc names no type an app cannot reach: every type in a signature, field or variant of
`cargo doc --no-deps -p holoface-headset-client` is a link (an item of the facade, or of the standard library and
other documented crates). A type written without a link is one the facade does not export, so an app could not name
it without depending on another holoface crate (issue 54). Usage: doc-links.py target/doc/holoface_headset_client"""
import html
import pathlib
import re
import sys

# Names rustdoc writes as plain text although they are not types of ours: the prelude, auto and blanket traits'
# associated names, and its own "Show n methods" toggles.
PLAIN = set(
    "Result Option Vec Arc String Box Self Rc Cow Duration Instant Path PathBuf Send Sync Sized Clone Copy Debug "
    "Default PartialEq Eq Hash Display Error From Into Fn FnMut FnOnce Iterator IntoIterator Formatter Ord "
    "PartialOrd Deref Drop AsRef Borrow ToOwned ToString TryFrom TryInto Any Unpin UnwindSafe RefUnwindSafe Freeze "
    "Output Target Item Err Mutex HashMap SocketAddr Ordering Infallible Future Pin FromStr StructuralPartialEq "
    "BorrowMut Owned Hasher Show".split()
)
CODE = re.compile(
    r'<(pre class="rust item-decl"|h3 class="code-header"|h4 class="code-header"'
    r'|span id="structfield[^"]*"[^>]*|section id="variant[^"]*"[^>]*)>(.*?)</(pre|h3|h4|span|section)>',
    re.S,
)


def unlinked(root: pathlib.Path) -> dict[str, set[str]]:
    local = {re.sub(r"^[a-z]+\.", "", p.stem) for p in root.rglob("*.html")}
    found: dict[str, set[str]] = {}
    for page in root.rglob("*.html"):
        text = page.read_text()
        # Auto and blanket trait impls list the traits' own generics (e.g. `T: ?Sized`): not the API.
        text = re.split(r'id="(?:synthetic-implementations|blanket-implementations)"', text)[0]
        variants = set(re.findall(r'id="variant\.([A-Za-z0-9_]+)"', text))
        for m in CODE.finditer(text):
            code = re.sub(r"<a [^>]*>.*?</a>", " ", m.group(2), flags=re.S)
            code = html.unescape(re.sub(r"<[^>]+>", " ", code))
            for word in re.findall(r"\b[A-Z][a-z][A-Za-z0-9]*\b", code):
                if word not in PLAIN and word not in local and word not in variants:
                    found.setdefault(word, set()).add(str(page.relative_to(root)))
    return found


def main() -> int:
    root = pathlib.Path(sys.argv[1])
    if not (root / "index.html").is_file():
        print(f"{root}: no rustdoc output here (run cargo doc first)", file=sys.stderr)
        return 2
    found = unlinked(root)
    for word in sorted(found):
        print(f"{word}: shown without a link in {', '.join(sorted(found[word])[:3])}", file=sys.stderr)
    if found:
        print(f"{len(found)} type(s) in the facade's docs that an app cannot name from it", file=sys.stderr)
        return 1
    print(f"{root.name}: every type in its docs links to an item an app can name")
    return 0


if __name__ == "__main__":
    sys.exit(main())
