"""Live puppetry: the per-tick marionette, the dispatcher over physics links, the worker process, the view.
"""
