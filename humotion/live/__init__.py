"""Live tracking: a headset in, a body out (docs/live.md).

- :mod:`humotion.live.vmc`: a body as VMC (OSC over UDP) for VTuber apps and game engines.
- :mod:`humotion.live.protocol`: the WebSocket messages of ``humotion serve`` (JSON and binary).
- :mod:`humotion.live.server`: the asyncio WebSocket server, one SparseTracker per connection.
"""
