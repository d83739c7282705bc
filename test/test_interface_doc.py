"""docs/interface.md's parameter tables are the typed configurations' (interface_doc)."""
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
