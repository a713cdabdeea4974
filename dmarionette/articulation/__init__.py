"""The puppet's articulated bodies: model, state, control and the implicit solver; MJCF export.
"""
