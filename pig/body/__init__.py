"""Skinned body model (SMPL-X layout), surface frames and anchor transport."""
