"""Images: safe decoding of untrusted files, colour conversions, working resolution, and overlays."""
