"""Gradients of marionette rollouts: a checkpointed engine that records the solver's own step on a tape.
"""
