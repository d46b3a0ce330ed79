"""Real-time streamer: audio sources in, gesture frames out over WebSocket, VMC/OSC and BVH."""
