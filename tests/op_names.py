"""A count of the aten ops dispatched while active, by name: for tests that a change removes work (not timing)."""
from collections import Counter

from torch.utils._python_dispatch import TorchDispatchMode


class OpNames(TorchDispatchMode):
    """The names of the aten ops dispatched while active."""

    def __init__(self):
        super().__init__()
        self.names = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.names[func._schema.name.split("::")[-1]] += 1
        return func(*args, **(kwargs or {}))
