"""Readable reference implementations the tests compare the project's code against."""
