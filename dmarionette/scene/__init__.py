"""Descriptions of what is simulated: scenes, puppets, control bars, their validation and the built-in scenes.

Nothing here imports a simulator: a description is data, checked when it is read.
"""
