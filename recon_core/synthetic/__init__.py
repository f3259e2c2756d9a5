"""The synthetic pushbroom site generator (tests, benchmarks, the demo); no reconstruction module imports it."""
