"""Contacts from ContactNet for a chair it has not seen (paper Sec. 4.4, supplementary Sec. 3):
sample the cVAE conditioned on the chair's voxels, then project each hand's contact onto the
chair surface if it is within 10 cm, else drop it (a "no contact" hand).
"""

from __future__ import annotations

import os

import numpy as np
import torch

from couch.geometry import apply_transform
from couch.synthesis.controller import Scene
from couch.synthesis.features import contact_net_condition, voxel_grid
from couch.synthesis.nets import project_contacts
from couch.synthesis.train import load_trained

__all__ = ["sample_contacts"]


def sample_contacts(run_dir: str | os.PathLike, scene: Scene, n: int, *, seed: int = 0,
                    which: str = "best", max_distance: float = 0.10,
                    device: str = "cpu") -> np.ndarray:
    """``n`` contact sets for ``scene``'s chair from the run's ContactNet.

    Returns:
        (n, 2, 3) world contact points (left, right hand); a hand whose sample lies farther than
        ``max_distance`` m from the chair surface is NaN (no contact).
    """
    if n < 1:
        raise ValueError(f"need at least one contact sample, got {n}")
    model, stats, meta = load_trained(run_dir, "contact", which, device)
    cfg = meta["feature_config"]
    occupancy, centres, _ = voxel_grid(scene.vertices, scene.faces,
                                       cfg["interaction_resolution"],
                                       cfg["interaction_subsamples"])
    cond = contact_net_condition(occupancy, centres)
    x = stats.normalize("contact_condition", cond[None]).astype(np.float32)
    gen = torch.Generator(device=device).manual_seed(seed)
    with torch.no_grad():
        raw = model.sample(torch.as_tensor(x, device=device), n, generator=gen)[0]
    chair = stats.denormalize("hand_contacts", raw.cpu().numpy().astype(np.float64))
    chair = chair.reshape(n, 2, 3) + centres.mean(0)  # relative to the chair centre
    projected, kept = project_contacts(chair.reshape(-1, 3), scene.vertices, scene.faces,
                                       max_distance)
    projected[~kept] = np.nan
    return apply_transform(scene.world_from_chair, projected.reshape(n, 2, 3))
