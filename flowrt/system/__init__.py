"""The operating system's side: priorities, real-time scheduling, the event loop."""
