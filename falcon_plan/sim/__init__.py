"""The simulated Falcon: its equations (:mod:`.equations`), firmware (:mod:`.firmware`),
batched runs (:mod:`.batch`), the plant itself (:mod:`.plant`) and the step experiment
(:mod:`.step`)."""
