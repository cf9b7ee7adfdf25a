"""The direction finder's datagrams in: the wire format, the socket, the scan buffer, scans paired with poses."""
