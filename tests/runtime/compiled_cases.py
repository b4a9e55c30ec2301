"""The test cases of a module, each with its model compiled once (a module fixture's body)."""
from symkf.runtime import load


def compiled_cases(makers: dict) -> dict:
    """{name: case} from {name: maker}, each case with ``compiled``: its model's compiled library."""
    made = {name: make() for name, make in makers.items()}
    for case in made.values():
        case["compiled"] = load(case["model"], backend="compiled")
    return made
