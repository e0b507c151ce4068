"""The aggregator daemon: the only code that knows Zenoh, the journal and the clock."""
