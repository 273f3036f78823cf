"""Built-in flowrt nodes. They use only flowrt's public API, like any third-party node."""
