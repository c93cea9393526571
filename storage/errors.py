"""Storage errors: a missing, corrupt or mismatched file or record (never a traceback)."""


class StoreError(Exception):
    """A store problem the user can act on; ``field`` names what is at fault (e.g. 'model')."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


class NotFound(StoreError):
    """No such model or session."""


class Conflict(StoreError):
    """A sequence gap or a concurrent update that must not be applied."""


class Unavailable(StoreError):
    """The store cannot take writes now: the disk is full (``retry_after`` seconds: space may come
    back), or the database was removed or damaged under the server (``retry_after`` None: an
    operator must restore it).  Nothing was stored, so nothing may be acknowledged."""

    def __init__(self, field: str, message: str, retry_after: int | None = None):
        super().__init__(field, message)
        self.retry_after = retry_after
