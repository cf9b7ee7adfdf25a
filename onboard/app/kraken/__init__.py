"""A KrakenSDR's DoA output as the app's DF input: the line, the fetch, the source."""
