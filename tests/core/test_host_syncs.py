"""The host-synchronisation counter finds the calls that make a host wait for a GPU, and only those."""

from __future__ import annotations

import torch

from spiral.core.host_syncs import HostSyncCounter


def _everywhere(_: str) -> bool:
    return True


def test_reads_index_searches_and_mask_indexing_are_counted():
    x, mask = torch.arange(6.0), torch.arange(6) > 2
    with HostSyncCounter(_everywhere) as syncs:
        bool(mask.any())
        float(x[0])
        x.tolist()
        mask.nonzero()
        torch.where(mask)
        x[mask]
        x[mask] = 0.0
        x.repeat_interleave(mask.long())
        torch.bincount(mask.long())
        x.cpu()
    calls = sorted(name for name, _ in syncs.sites.elements())
    assert calls == sorted(["__bool__", "__float__", "tolist", "nonzero", "where", "__getitem__", "__setitem__",
                            "repeat_interleave", "bincount", "cpu"])
    assert syncs.total == 10  # exact: a count of calls


def test_device_side_masks_and_fixed_size_indexing_are_not_counted():
    x, mask, idx = torch.arange(6.0), torch.arange(6) > 2, torch.tensor([0, 2])
    with HostSyncCounter(_everywhere) as syncs:
        torch.where(mask, x, 0.0)
        x.masked_fill(mask, 1.0)
        x[idx]
        x[idx] = 3.0
        x[1:4]
        x.to(x.device)  # on a CPU env: the env's device, no copy to a host
        x.repeat_interleave(2)
        mask.any()
        (x * mask).sum()
    assert syncs.total == 0  # exact: a count of calls


def test_call_sites_name_the_file_and_line_that_called():
    x = torch.ones(3)
    with HostSyncCounter(_everywhere) as syncs:
        x.sum().item()
    ((name, site),) = syncs.sites
    assert name == "item"
    assert site.startswith(__file__.rsplit("/spiral/", 1)[-1]) or "test_host_syncs.py" in site
