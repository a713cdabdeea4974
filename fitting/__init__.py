"""fitting: optimisation on top of dmarionette (JAX + optimistix): keyframe authoring, calibration.

This package may import ``dmarionette``; ``dmarionette`` never imports it. Its contents arrive
with the differentiable-rollouts issue; the simulator's Warp-tape gradients it will wrap are
tested in tests/test_string_gradients.py.
"""
