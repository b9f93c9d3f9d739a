"""Retarget: influence regions to joint weights on a face mesh, rig exports, marker guides."""

__all__: list[str] = []
