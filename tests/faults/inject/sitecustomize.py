"""Test helper, on PYTHONPATH only in children started by kit.signal_at_import: sends the process
a signal while it imports the module named by DEPTHNAV_TEST_SIGNAL_AT, from an import hook (so
at the same point of start-up every run), optionally from inside a weakref callback."""

import os
import sys
import weakref

_AT = os.environ.get("DEPTHNAV_TEST_SIGNAL_AT")
_SIG = int(os.environ.get("DEPTHNAV_TEST_SIGNAL", "0"))
_IN_CALLBACK = bool(os.environ.get("DEPTHNAV_TEST_SIGNAL_IN_CALLBACK"))


class _SignalOnImport:
    def find_spec(self, name, path=None, target=None):
        if name != _AT:
            return None
        sys.meta_path.remove(self)
        if _IN_CALLBACK:

            class _Dies:
                pass

            victim = _Dies()
            ref = weakref.ref(victim, lambda _ref: os.kill(os.getpid(), _SIG))
            del victim  # the callback runs now, inside the import; its exceptions are ignored
            del ref
        else:
            os.kill(os.getpid(), _SIG)
        return None


if _AT and _SIG:
    sys.meta_path.insert(0, _SignalOnImport())
