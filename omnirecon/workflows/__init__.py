"""What each command does, as a library function of its options: the verbs composed by `demo`
and `reconstruct`. Each module holds one verb's options dataclass and its run function."""
