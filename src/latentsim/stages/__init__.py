"""The function each rule's script calls: one module per rule file of ``workflow/rules/``."""
