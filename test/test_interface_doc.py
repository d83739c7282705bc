"""The generated tables of the docs are current: parameters (docs/interface.md), safety."""
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.schema import specs
from wheelleg_balance.validation import interface_doc


def test_the_parameter_tables_are_current():
    text = interface_doc.PAGE.read_text()
    assert interface_doc.render(text) == text, \
        'run: python -m wheelleg_balance.validation.interface_doc --write'


def test_every_node_has_its_table_and_every_parameter_a_row():
    text = interface_doc.PAGE.read_text()
    for node in interface_doc.node_configs():
        assert '<!-- parameters:%s -->' % node in text
    for s in specs(BalanceConfig):
        assert '| `%s` |' % s.name in text


def test_a_changed_default_makes_the_page_stale(monkeypatch):
    text = interface_doc.PAGE.read_text()
    real = interface_doc.parameter_table

    def changed(cls):
        out = real(cls)
        return out.replace('| `body_mass` | float | 11 |', '| `body_mass` | float | 12 |')
    monkeypatch.setattr(interface_doc, 'parameter_table', changed)
    assert interface_doc.render(text) != text


def test_every_fault_and_warning_code_has_a_row_of_the_safety_table():
    from wheelleg_balance.core import safety
    codes = safety.FAULT_CODES + safety.WARNING_CODES
    assert {'response', 'encoder_mismatch', 'input_conflict', 'lifted'} <= set(codes)
    assert set(safety.SAFETY_TABLE) == set(codes)
    for code, row in safety.SAFETY_TABLE.items():
        assert all(text.strip() for text in row), code
    text = interface_doc.SAFETY_PAGE.read_text()
    for code in codes:
        assert '| `%s` |' % code in text, code


def test_the_safety_table_of_docs_balance_node_is_current():
    text = interface_doc.SAFETY_PAGE.read_text()
    assert interface_doc.render_safety(text) == text, \
        'run: python -m wheelleg_balance.validation.interface_doc --write'


def test_a_changed_reaction_makes_the_safety_page_stale(monkeypatch):
    from wheelleg_balance.core import safety
    text = interface_doc.SAFETY_PAGE.read_text()
    row = safety.SAFETY_TABLE['fall']
    monkeypatch.setitem(safety.SAFETY_TABLE, 'fall', row._replace(reaction='nothing'))
    assert interface_doc.render_safety(text) != text
