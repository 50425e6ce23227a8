"""One thin module per CLI verb: a tyro dataclass config whose ``main()`` calls the library.
No command imports another command."""
