"""Simulation campaigns: campaign files, pose sampling, the dataset writer/reader and the runner.

``load_campaign(path)`` reads a campaign file (:mod:`sim.campaign.config`);
``run_campaign(cfg, out)`` renders it (:mod:`sim.campaign.runner`, also ``ctxreg simulate``);
``open_dataset(DIR)`` reads the result without PyTorch (:mod:`sim.campaign.dataset`).
"""

from sim.campaign.config import load_campaign
from sim.campaign.dataset import CampaignDataset, DatasetError, open_dataset


def run_campaign(*args, **kwargs):
    """See :func:`sim.campaign.runner.run_campaign` (imported on use: it pulls in the renderer)."""
    from sim.campaign.runner import run_campaign as run  # imported on use: the renderer and the process pool

    return run(*args, **kwargs)


__all__ = ["load_campaign", "open_dataset", "run_campaign", "CampaignDataset", "DatasetError"]
