"""Live puppetry: the per-tick marionette (physics), the session set-up (setup, record), one link
per physics mode (links, process), the dispatcher (run) and the live view (view, view_viser).

Imports point one way: view <- physics <- record <- setup <- process <- links <- run.
"""
