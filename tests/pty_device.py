"""A device thread on a pty master for the tests: answers HELLO_REQUEST and PING itself and
hands every other message to a hook (shared by test_compiled_loop.py and
test_velocity_wire.py, which script different devices on top of it)."""

from __future__ import annotations

import os
import select
import threading

import firmware_protocol as fp


class PtyDevice(threading.Thread):
    """Reads and decodes what the host writes on ``master``; HELLO for HELLO_REQUEST
    (``hello``, an encoded frame), PONG for PING; :meth:`on_message` for the rest and
    :meth:`tick` after every wait (``tick`` returns how long the next wait may be [s]).
    Stops when :attr:`done` is set or the pty closes."""

    def __init__(self, master: int, hello: bytes) -> None:
        super().__init__(daemon=True)
        self.master = master
        self.hello = hello
        self.done = False

    def on_message(self, msg) -> None:
        """A decoded message other than HELLO_REQUEST and PING."""

    def tick(self) -> float:
        """After every wait (input or not); the next wait's timeout [s]."""
        return 0.01

    def run(self) -> None:
        dec = fp.StreamDecoder()
        timeout = 0.01
        while not self.done:
            r, _, _ = select.select([self.master], [], [], timeout)
            if r:
                try:
                    data = os.read(self.master, 65536)
                except OSError:
                    return
                for msg in dec.feed(data):
                    t = type(msg)
                    if t is fp.HelloRequest:
                        os.write(self.master, self.hello)
                    elif t is fp.Ping:
                        os.write(self.master, fp.encode(fp.Pong(msg.nonce, msg.host_time_us, 0)))
                    else:
                        self.on_message(msg)
            timeout = self.tick()
