"""dmarionette: a differentiable simulator of a string marionette."""
