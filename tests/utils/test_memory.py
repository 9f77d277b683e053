"""retain_freed_memory: glibc keeps freed memory, so re-allocating a freed tensor takes no page faults."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from lightning_vtr.utils import memory

# A child process frees a 24 MiB tensor (glibc's adaptive threshold at start maps it on its own and unmaps it when it
# is freed; ours keeps it in the heap), then allocates and fills a 20 MiB one, counting the page faults that take.
_CHILD = """
import json, resource, sys, torch
from lightning_vtr.utils.memory import retain_freed_memory
retained = retain_freed_memory() if sys.argv[1] == "retain" else None
torch.empty(6 * 2**20).fill_(1.0)  # 24 MiB allocated, touched, freed
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
torch.empty(5 * 2**20).fill_(1.0)  # 20 MiB: fits in the freed block wherever it lies
print(json.dumps({"retained": retained, "faults": resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before}))
"""

glibc_only = pytest.mark.skipif(
    sys.platform != "linux" or platform.libc_ver()[0] != "glibc", reason="the setting is glibc's"
)


def _child(mode: str, **env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if k not in memory.USER_SETTINGS}
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, mode], env={**clean, **env}, capture_output=True, text=True, check=True
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


@glibc_only
def test_freed_memory_is_reused_without_page_faults_once_retained():
    pages = 20 * 2**20 // 4096  # 5,120 pages of 4 KiB
    default = _child("default")
    retained = _child("retain")
    assert default["faults"] > pages // 2  # the freed block went back to the system; its pages are taken again
    assert retained["retained"] is True
    assert retained["faults"] < pages // 20


@glibc_only
def test_a_user_setting_of_the_allocator_is_left_alone():
    child = _child("retain", MALLOC_TRIM_THRESHOLD_="1000")
    assert child["retained"] is False


def test_off_linux_it_does_nothing(monkeypatch):
    monkeypatch.setattr(memory.sys, "platform", "darwin")
    assert memory.retain_freed_memory() is False
