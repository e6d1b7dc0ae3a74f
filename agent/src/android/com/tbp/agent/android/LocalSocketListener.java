package com.tbp.agent.android;

import android.net.LocalServerSocket;
import android.net.LocalSocket;
import com.tbp.agent.Agent;
import com.tbp.agent.Log;
import com.tbp.agent.StreamConnection;
import java.io.Closeable;
import java.io.IOException;

/**
 * The agent's abstract UNIX socket ({@code localabstract:NAME} for adb): each client a
 * {@link StreamConnection}. An agent started while the previous one still exits finds the name
 * taken for a moment; binding is retried for {@value #BIND_RETRY_MS} ms.
 */
final class LocalSocketListener implements Closeable {

    static final long BIND_RETRY_MS = 2000;

    private final LocalServerSocket server;
    private volatile boolean closed;

    private LocalSocketListener(LocalServerSocket server) {
        this.server = server;
    }

    static LocalSocketListener start(String name, final Agent agent, final Log log) throws IOException {
        final LocalSocketListener listener = new LocalSocketListener(bind(name));
        Thread acceptor = new Thread(new Runnable() {
            @Override
            public void run() {
                listener.accept(agent, log);
            }
        }, "accept-" + name);
        acceptor.setDaemon(true);
        acceptor.start();
        return listener;
    }

    private static LocalServerSocket bind(String name) throws IOException {
        long deadline = System.nanoTime() + BIND_RETRY_MS * 1_000_000L;
        while (true) {
            try {
                return new LocalServerSocket(name);
            } catch (IOException taken) {
                if (System.nanoTime() > deadline) {
                    throw new IOException("cannot bind the abstract socket " + name + ": " + taken.getMessage(), taken);
                }
            }
            try {
                Thread.sleep(100);
            } catch (InterruptedException e) {
                throw new IOException("interrupted while binding " + name, e);
            }
        }
    }

    private void accept(Agent agent, Log log) {
        int clients = 0;
        while (!closed) {
            LocalSocket socket;
            try {
                socket = server.accept();
            } catch (IOException e) {
                if (!closed) {
                    log.error("accept failed", e);
                }
                return;
            }
            try {
                new StreamConnection("client-" + (++clients), socket.getInputStream(), socket.getOutputStream(), socket,
                        agent, log).start();
            } catch (IOException e) {
                log.error("a client's streams", e);
                try {
                    socket.close();
                } catch (IOException closing) {
                    log.info("closing a client without streams: " + closing.getMessage());
                }
            }
        }
    }

    /** Stops taking clients. A thread blocked in accept() stays blocked; the process exits next. */
    @Override
    public void close() throws IOException {
        closed = true;
        server.close();
    }
}
