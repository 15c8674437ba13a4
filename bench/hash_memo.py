"""What the hash memo's stricter trust costs on 1,000 photos (pipeline.core.hashing).

    .venv/bin/python -m bench.hash_memo [--photos 1000] [--megabytes 4] [--work /tmp/hash-memo] [--write]

Writes ``--photos`` files of random bytes (photo-sized), then times: the first pass,
which hashes every file; a pass right after, where files whose ctime lies within
RACY_NS of their hashing are read again; a pass once every file is old enough (only
stat); and a pass after one file was replaced with ``cp -p`` semantics (same size and
mtime), which must read that file. Files sit in the page cache: the times are the
hashing's, not a disk's.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from bench.common import write_section

SECTION = "## The hash memo's cost (issue 53)"


def timed_pass(memo: Path, files: list[Path]) -> tuple[float, int]:
    from pipeline.core.hashing import FileHasher

    hasher = FileHasher(memo)
    started = time.perf_counter()
    for path in files:
        hasher.hash(path)
    seconds = time.perf_counter() - started
    hasher.save()
    return seconds, hasher.files_read


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--photos", type=int, default=1000)
    parser.add_argument("--megabytes", type=float, default=4.0)
    parser.add_argument("--work", default="/tmp/hash-memo")
    parser.add_argument("--write", action="store_true")
    args = parser.parse_args()
    from pipeline.core.hashing import RACY_NS

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    memo = work / "file_hashes.json"
    memo.unlink(missing_ok=True)
    size = int(args.megabytes * 1e6)
    files = []
    for index in range(args.photos):
        path = work / f"photo_{index:04d}.jpg"
        path.write_bytes(os.urandom(size))
        files.append(path)
    rows = [("first pass (every file read)", *timed_pass(memo, files))]
    rows.append(("right after (files changed within 2 s of their hashing are read again)", *timed_pass(memo, files)))
    time.sleep(RACY_NS / 1e9 + 0.5)
    rows.append(("every file older than 2 s (stat only)", *timed_pass(memo, files)))
    stamp = files[0].stat()
    files[0].write_bytes(os.urandom(size))
    os.utime(files[0], ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
    time.sleep(RACY_NS / 1e9 + 0.5)
    rows.append(("one file replaced, same size and mtime (cp -p)", *timed_pass(memo, files)))
    lines = [
        SECTION,
        "",
        f"Machine: the 2-core development VM. Command: `.venv/bin/python -m bench.hash_memo --photos {args.photos} "
        f"--megabytes {args.megabytes:g}`; files in the page cache.",
        "",
        "| pass | seconds | files read |",
        "|---|---|---|",
        *(f"| {name} | {seconds:.3f} | {read} |" for name, seconds, read in rows),
        "",
    ]
    print("\n".join(lines))
    if args.write:
        write_section("hash-memo", lines)
    for path in files:
        path.unlink()
    return 0


if __name__ == "__main__":
    sys.exit(main())
