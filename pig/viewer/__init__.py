"""The browser viewer (`python -m pig.stages.view`): a fitted avatar in viser's web page, orbit, timeline, LOD, capture cameras.

A layer above pig.avatar (it drives an `AvatarDriver`) and below pig.stages; viser is imported only here (the
`viewer` extra).
"""
