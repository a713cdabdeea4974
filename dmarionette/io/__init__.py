"""Files: trajectories, recorded sessions (MCAP) and motion exports (BVH, glTF).
"""
