"""Print the first ```bash block after the first README line that starts with a marker (CI runs it as written)."""

import sys
from pathlib import Path


def block_after(text: str, marker: str) -> str:
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines) if line.startswith(marker)), None)
    if start is None:
        raise SystemExit(f"no line starting with {marker!r}")
    fence = next(i for i in range(start, len(lines)) if lines[i].strip() == "```bash")
    end = next(i for i in range(fence + 1, len(lines)) if lines[i].strip() == "```")
    return "\n".join(lines[fence + 1 : end])


if __name__ == "__main__":
    readme, marker = sys.argv[1], sys.argv[2]
    print(block_after(Path(readme).read_text(encoding="utf-8"), marker))
