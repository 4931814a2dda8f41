"""The opponent pool: a member whose checksum fails is reported and skipped."""

from __future__ import annotations

import json

from spiral.selfplay import Pool


def test_pool_skips_a_member_whose_checksum_fails(tmp_path):
    """Report and skip a corrupted member instead of failing."""
    pool = Pool(tmp_path)
    pool.members = []
    (tmp_path / "pool.json").write_text(json.dumps({"latest_best": "x", "members": [
        {"id": "x", "file": "x.pt", "stage": "solo", "iteration": 0, "sha256": "00"}]}))
    (tmp_path / "x.pt").write_bytes(b"garbage")
    logs: list[str] = []
    assert Pool(tmp_path, log=logs.append).load_policies({"obs_dim": 1}) == {}
    assert "pool member x skipped" in logs[0]
