"""What a service consumes and produces on the network, declared with the service (its class's ``PORTS``), as a
Drake system declares its input and output ports: the key (named by the :class:`~protocol.keys.Keys` attribute that
spells it; a method such as ``controller_api`` stands for every key it makes) and the message type it carries.

:class:`~services.runtime.service.Service` refuses to subscribe to, publish on or answer a key its class does not
declare (:class:`UndeclaredPort`), so the declaration is what the service does; ``tests/services/runtime/
test_ports.py`` holds every declaration to ``protocol/topics.py``, and ``mfvs keys --graph`` draws the stack from
them (:func:`graph`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from protocol.keys import Keys
from protocol.messages import ServiceHealth, SimClock


class UndeclaredPort(RuntimeError):
    """A service used a key its class does not declare."""


@dataclass(frozen=True)
class Port:
    #: the attribute of Keys that spells the key (a property, or a method standing for every key it makes)
    key: str
    #: what it carries (None for a query's key)
    message_type: Optional[type] = None

    def _made_below(self, keys: Keys) -> Optional[str]:
        """For a method of Keys: the key every key it makes sits directly below; None for a property."""
        if isinstance(getattr(type(keys), self.key), property):
            return None
        return getattr(keys, self.key)("_").rsplit("/", 1)[0]

    def keys_of(self, keys: Keys) -> str:
        """The key, or for a method the key expression of every key it makes (``*`` for its argument)."""
        below = self._made_below(keys)
        return getattr(keys, self.key) if below is None else below + "/*"

    def matches(self, keys: Keys, key: str) -> bool:
        below = self._made_below(keys)
        return key == getattr(keys, self.key) if below is None else key.rsplit("/", 1)[0] == below


@dataclass(frozen=True)
class Ports:
    #: subscribed topics
    consumes: tuple[Port, ...] = ()
    #: published topics
    produces: tuple[Port, ...] = ()
    #: queries answered (their keys)
    answers: tuple[Port, ...] = ()

    def find(self, kind: str, keys: Keys, key: str, message_type: Optional[type] = None) -> Port:
        """The declared port of ``kind`` (consumes, produces, answers) for ``key``; raises UndeclaredPort if there
        is none, or if it carries another type."""
        for port in getattr(self, kind):
            if port.matches(keys, key):
                if message_type is not None and port.message_type is not message_type:
                    raise UndeclaredPort(f"{key} is declared to carry {port.message_type.__name__}, "
                                         f"not {message_type.__name__}")
                return port
        raise UndeclaredPort(f"{key} is not among the keys it {kind}: declare it in the class's PORTS")

    def __or__(self, other: "Ports") -> "Ports":
        return Ports(self.consumes + other.consumes, self.produces + other.produces, self.answers + other.answers)


#: what every service does besides its own (services.runtime.service.Service): its health, on a key and as a query,
#: and in lockstep the simulator's clock
EVERY_SERVICE = Ports(consumes=(Port("clock", SimClock),), produces=(Port("health", ServiceHealth),),
                      answers=(Port("health"),))


def graph(services: dict[str, Ports], keys: Keys | None = None) -> list[tuple[str, str, list[str], list[str]]]:
    """The stack as its services declare it: for each topic, (key, message type, who publishes it, who subscribes
    to it), in the order of the keys."""
    keys = keys or Keys()
    topics: dict[str, tuple[str, list[str], list[str]]] = {}
    for name, ports in services.items():
        for kind, port_list in (("produces", ports.produces), ("consumes", ports.consumes)):
            for port in port_list:
                key = port.keys_of(keys)
                type_name = port.message_type.__name__ if port.message_type is not None else "-"
                entry = topics.setdefault(key, (type_name, [], []))
                (entry[1] if kind == "produces" else entry[2]).append(name)
    return [(key, t, sorted(set(pubs)), sorted(set(subs))) for key, (t, pubs, subs) in sorted(topics.items())]
