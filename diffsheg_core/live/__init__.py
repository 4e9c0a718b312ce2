"""Live generation: speech arriving from a microphone, a file played at real time or a
socket drives the avatar within a fraction of a second, and is recorded.

- feed.py     the bounded, thread-safe audio queue between a source and the generator
- sources.py  microphone, file at real time, TCP socket
- engine.py   the low-latency streaming sampler: a FOPPAS window per hop of new frames
- session.py  a source, the engine and the outputs run together; latency, underruns, recording
- vmc.py      the VMC protocol over OSC (VSeeFace, Warudo, VNyan)
- cli.py      `python -m diffsheg_core live`
"""
