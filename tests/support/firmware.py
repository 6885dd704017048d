"""What the firmware tests share: build the firmware and the simavr harness once, or say why
not. A missing toolchain skips them with the install command; with DDRT_REQUIRE_FIRMWARE=1
(.ci/run sets it, as CI installs the packages) it fails them instead, so CI cannot pass
without having run them."""

from __future__ import annotations

import os

import pytest

from sim_hal import firmware_build

_built: set[str] = set()


def require(*targets: str) -> None:
    """Build these make targets (once per session), or skip / fail the test."""
    missing = firmware_build.missing_tools(*targets)
    if missing:
        reason = (f"AVR toolchain / simavr not installed ({', '.join(missing)} missing); "
                  f"install with: {firmware_build.INSTALL_HINT}")
        if os.environ.get("DDRT_REQUIRE_FIRMWARE"):
            pytest.fail(reason)
        pytest.skip(reason)
    todo = [t for t in targets if t not in _built]
    if todo:
        firmware_build.build(*todo)
        _built.update(todo)
