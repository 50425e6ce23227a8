"""The CLI verbs: thin tyro dataclass configs whose ``main()`` parses and calls the library."""
