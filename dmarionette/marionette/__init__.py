"""The marionette: strings, puppet and bars coupled (paper §2-4); its rollout, energy and accuracy sweep.
"""
