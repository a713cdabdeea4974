"""Pictures and animations of rollouts (matplotlib).
"""
