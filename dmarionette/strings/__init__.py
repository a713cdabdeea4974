"""The strings (paper §2.2): their model, the implicit stepper and rollouts.
"""
