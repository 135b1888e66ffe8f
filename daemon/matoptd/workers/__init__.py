"""The renderer workers: the daemon's handle on each (a local process or a Ray actor), the
worker's own side (one engine answering calls), and the devices they run on."""
