"""The file layer of a run file: restorable to its last flush, locked while written.

HDF5 updates its metadata in place.  A write that fails half-way (a full disk, an I/O error)
or a process killed between the writes of one flush leaves B-trees that point past the end of
the file ("addr overflow"): measured on a 300 kB tmpfs, the file of the run that filled it
could not be read at all.  So the writer hands HDF5 a `JournaledFile` (h5py's fileobj driver):
before a byte range that existed at the last commit (the end of a completed flush, when the
file is consistent) is overwritten or cut off, its old bytes are appended to OUT.h5.journal;
`commit()` empties the journal.  A rollback puts the file back into its state at the last
commit: the saved bytes written back (newest first), the bytes appended since cut off.  The
writer rolls back itself when a write fails; `recover(path)` does it for the file of a process
that died mid-write (the readers and `--restart` call it).  Bytes past the committed size need
no journal (they are cut off), so appending a frame journals only the few metadata blocks
HDF5 rewrites (object headers, index nodes).  Process death and I/O errors are covered, not a
crash of the machine (no fsync).

The writer holds an exclusive flock on the file while it is open: a second writer, and a
reader that locks (HDF5's default), fail at once with "in use by another process".
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import io
import os
import struct

_MAGIC = b"VFJ1"
_HEAD = struct.Struct("<4sQ")        # magic, committed size
_ENTRY = struct.Struct("<QQ")        # offset, length; then the old bytes
_OPEN = {}                           # (device, inode) -> the JournaledFile this process writes


class FileInUse(OSError):
    """Another process holds the lock of the file."""


def journal_path(path):
    return os.fspath(path) + ".journal"


def lock_exclusive(fd, path):
    """flock(LOCK_EX | LOCK_NB) on fd; FileInUse when another process holds a lock."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        if e.errno in (errno.EAGAIN, errno.EACCES):
            raise FileInUse(e.errno, f"{os.fspath(path)} is in use by another process") from None
        if e.errno not in (errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP, errno.EINVAL):
            raise
        # a file system without flock: nothing can be locked, and HDF5's own lock fails there too


class JournaledFile(io.RawIOBase):
    """A read-write file object for h5py.File(obj, mode): journaled writes, exclusive lock.

    JournaledFile(path, create=False): create truncates (or creates) the file, after the lock is
    taken.  After a failed write (`error` set) the file on disk is rolled back to the last
    commit and every later write goes to memory only.
    """

    def __init__(self, path, create=False):
        super().__init__()
        self.path = os.fspath(path)
        fd = os.open(self.path, os.O_RDWR | (os.O_CREAT if create else 0), 0o666)
        try:
            lock_exclusive(fd, self.path)
            if create:
                _truncate(fd, 0)
            else:
                _rollback_locked(fd, self.path)      # a journal left by a killed writer
            self._jfd = os.open(journal_path(self.path), os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666)
        except BaseException:
            os.close(fd)
            raise
        self.fd = fd
        st = os.fstat(fd)
        self._key = (st.st_dev, st.st_ino)
        _OPEN[self._key] = self
        self.pos = 0
        self.size = st.st_size
        self.error = None           # the OSError of the first failed write
        self.rollback_error = None  # an OSError of the rollback after it (the journal is kept)
        self._memory = None         # after a failure: [(offset, bytes)] kept in memory
        self.commit()

    # ------------------------------------------------------------------ journal
    def commit(self):
        """The file is consistent (HDF5 has flushed): forget the journal."""
        if self._memory is not None:
            return
        self.committed = self.size
        self._written = []          # (offset, length) written since the commit
        try:
            _truncate(self._jfd, 0)
            _write_all(self._jfd, _HEAD.pack(_MAGIC, self.committed), 0)
        except OSError as e:        # the file itself is consistent: nothing to roll back
            self.error, self._memory = e, []
        self._jend = _HEAD.size

    def _save(self, offset, length):
        """Journal the old bytes of [offset, offset + length) below the committed size."""
        end = min(offset + length, self.committed)
        if offset >= end:
            return
        old = os.pread(self.fd, end - offset, offset)
        rec = _ENTRY.pack(offset, len(old)) + old
        _write_all(self._jfd, rec, self._jend)
        self._jend += len(rec)

    def _fail(self, e, pending):
        """A write failed: note the error, roll the disk back to the last commit and keep
        HDF5's view (what it wrote since, and `pending`) in memory.  HDF5 is told nothing:
        its handle stays sane and closes without touching the disk; the writer reads `error`
        after each of its operations."""
        self.error = e
        overlay = []
        for off, n in self._written:
            try:
                overlay.append((off, os.pread(self.fd, n, off)))
            except OSError:
                pass
        overlay.append(pending)
        try:
            _apply(self.fd, self._jfd)
        except OSError as e2:              # the journal stays: recover() retries later
            self.rollback_error = e2
        self._memory = overlay

    # ------------------------------------------------------------------ file object
    def readable(self):
        return True

    def writable(self):
        return True

    def seekable(self):
        return True

    def seek(self, offset, whence=io.SEEK_SET):
        if whence == io.SEEK_SET:
            self.pos = offset
        elif whence == io.SEEK_CUR:
            self.pos += offset
        else:
            self.pos = self.size + offset
        return self.pos

    def tell(self):
        return self.pos

    def readinto(self, b):
        m = memoryview(b).cast("B")
        n = len(m)
        data = os.pread(self.fd, n, self.pos)
        m[:len(data)] = data
        if len(data) < n:
            m[len(data):] = bytes(n - len(data))
        if self._memory:
            for off, buf in self._memory:      # what was written after the failure
                lo, hi = max(off, self.pos), min(off + len(buf), self.pos + n)
                if lo < hi:
                    m[lo - self.pos:hi - self.pos] = buf[lo - off:hi - off]
        self.pos += n
        return n

    def read(self, n=-1):
        if n is None or n < 0:
            n = max(self.size - self.pos, 0)
        b = bytearray(n)
        self.readinto(b)
        return bytes(b)

    def write(self, b):
        data = bytes(b)
        if self._memory is not None:
            self._memory.append((self.pos, data))
        else:
            try:
                self._save(self.pos, len(data))
                self._written.append((self.pos, len(data)))
                _write_all(self.fd, data, self.pos)
            except OSError as e:
                self._fail(e, (self.pos, data))
        self.pos += len(data)
        self.size = max(self.size, self.pos)
        return len(data)

    def truncate(self, size=None):
        size = self.pos if size is None else int(size)
        if self._memory is None:
            try:
                if size < self.size:
                    self._save(size, self.size - size)
                _truncate(self.fd, size)
            except OSError as e:
                self._fail(e, (size, b""))
        self.size = size
        return size

    def flush(self):
        pass

    def close(self):
        """Close and unlock; the journal is removed unless a rollback is still owed."""
        if self.closed:
            return
        try:
            if getattr(self, "_jfd", None) is not None:
                os.close(self._jfd)
                self._jfd = None
                if self.rollback_error is None:
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(journal_path(self.path))
            os.close(self.fd)
        finally:
            _OPEN.pop(self._key, None)
            super().close()


def _truncate(fd, size):
    """Every change of a file's size and every write of the layer go through _truncate and
    _write_all (the fault-injection tests replace them)."""
    os.ftruncate(fd, size)


def _write_all(fd, data, offset):
    view = memoryview(data)
    while len(view):
        n = os.pwrite(fd, view, offset)
        if n <= 0:
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        view, offset = view[n:], offset + n


def _apply(fd, jfd):
    """Write the journal's saved bytes back (newest first) and cut the file to the committed
    size.  A torn last record (the process died while writing it) is skipped: its data write
    had not begun."""
    raw = os.pread(jfd, os.fstat(jfd).st_size, 0)
    if len(raw) < _HEAD.size or raw[:4] != _MAGIC:
        return False                  # empty: killed right at a commit, the file is consistent
    _, committed = _HEAD.unpack_from(raw, 0)
    records, k = [], _HEAD.size
    while k + _ENTRY.size <= len(raw):
        off, n = _ENTRY.unpack_from(raw, k)
        if k + _ENTRY.size + n > len(raw):
            break
        records.append((off, raw[k + _ENTRY.size:k + _ENTRY.size + n]))
        k += _ENTRY.size + n
    for off, old in reversed(records):
        _write_all(fd, old, off)
    if os.fstat(fd).st_size != committed:
        _truncate(fd, committed)
    return True


def _rollback_locked(fd, path):
    """Roll the file open on fd (locked) back by its journal, if one was left; remove it."""
    jp = journal_path(path)
    if not os.path.exists(jp):
        return False
    jfd = os.open(jp, os.O_RDONLY)
    try:
        done = _apply(fd, jfd)
    finally:
        os.close(jfd)
    os.unlink(jp)
    return done


def written_here(path):
    """True if this process has the file open for writing (a JournaledFile): it is then
    consistent on disk after each of the writer's operations, and read without a lock."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    return (st.st_dev, st.st_ino) in _OPEN


def recover(path):
    """Roll back a run file left mid-write by a process that died (a journal beside it and
    nobody holding the lock).  True if it was rolled back; raises FileInUse if its writer is
    still running.  A file without a journal is left alone (no write access needed)."""
    if not os.path.exists(journal_path(path)):
        return False
    fd = os.open(os.fspath(path), os.O_RDWR)
    try:
        lock_exclusive(fd, path)
        return _rollback_locked(fd, os.fspath(path))
    finally:
        os.close(fd)


def check_not_in_use(path):
    """FileInUse if another process holds the lock of the file at path (a missing file is free)."""
    try:
        fd = os.open(os.fspath(path), os.O_RDONLY)
    except FileNotFoundError:
        return
    try:
        lock_exclusive(fd, path)
    finally:
        os.close(fd)
