"""The workflows behind the commands, as plain functions (usable from Python; the command modules only parse).

Every function takes an opened :class:`~labcal.datasets.SessionStore` and returns data; nothing here prints.
Errors the user can fix are raised as :class:`~labcal.cli.common.UserError` (or the library's ValueError subclasses)
with a message that names the bad input.

Submodules: ``common`` (robot model, pooled observations), ``fitting``, ``exporting``, ``evaluating``, ``refit``,
``sessions``, ``imports``, ``programs``; the store (``open_store``) and ``UserError`` are :mod:`labcal.cli.common`'s.
"""
