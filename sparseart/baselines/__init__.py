"""Peer baselines run side by side with sparseart on the same scenes and metrics."""
from .icp_peer import PeerOptions, icp_peer, icp_peer_from_result, register_part_icp

__all__ = ["PeerOptions", "icp_peer", "icp_peer_from_result", "register_part_icp"]
