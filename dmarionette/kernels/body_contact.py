"""placeholder"""
from dataclasses import dataclass


@dataclass(frozen=True)
class ContactSettings:
    ground: bool = False


class ContactSet:
    def __init__(self, model):
        self.model = model

    def eval(self, state, h):
        return
