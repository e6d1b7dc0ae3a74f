package com.tbp.agent;

import static org.junit.Assert.assertEquals;
import static org.junit.Assert.assertFalse;
import static org.junit.Assert.assertTrue;

import java.io.ByteArrayOutputStream;
import java.io.Closeable;
import java.io.File;
import java.io.PipedInputStream;
import java.io.PipedOutputStream;
import java.io.PrintStream;
import java.nio.charset.StandardCharsets;
import org.junit.Test;

/** The agent's life: READY after the camera and socket, the end when its shell stream closes. */
public class LauncherTest {

    private final Fakes.Camera camera = new Fakes.Camera();
    private final Fakes.FakePlatform platform = new Fakes.FakePlatform(camera);

    private final ByteArrayOutputStream printed = new ByteArrayOutputStream();

    private int run(PipedInputStream shell, String... args) throws InterruptedException {
        return Launcher.run(args, platform, shell, new PrintStream(printed, true));
    }

    private String output() {
        return new String(printed.toByteArray(), StandardCharsets.UTF_8);
    }

    @Test
    public void printsReadyAndExitsWhenTheShellStreamCloses() throws Exception {
        final PipedOutputStream host = new PipedOutputStream();
        final PipedInputStream shell = new PipedInputStream(host);
        final int[] status = {-1};
        Thread agent = new Thread(new Runnable() {
            @Override
            public void run() {
                try {
                    status[0] = LauncherTest.this.run(shell, "socket=tbp-test", "version=1", "later=ignored");
                } catch (InterruptedException e) {
                    Thread.currentThread().interrupt();
                }
            }
        });
        agent.start();
        for (int i = 0; i < 1000 && !output().contains("\n"); i++) {
            Thread.sleep(10);
        }
        assertEquals("TBP-CAPTURE-AGENT READY tbp-test 1\n", output());
        assertTrue(agent.isAlive());
        host.write("anything the shell sends is ignored\n".getBytes(StandardCharsets.UTF_8));
        host.close();
        agent.join(20_000);  // a generous bound: the agent ends on its own once its stdin ends
        assertFalse(agent.isAlive());
        assertEquals(0, status[0]);
        assertTrue(camera.closed);
        assertEquals(1, platform.listenerClosed.get());
        Thread.sleep(Launcher.EXIT_DEADLINE_MS + 200);  // the exit deadline does not fire after a clean end
    }

    @Test
    public void anotherProtocolVersionOrABadArgumentNeverStarts() throws Exception {
        assertEquals(2, run(new PipedInputStream(new PipedOutputStream()), "socket=tbp-capture", "version=2"));
        assertTrue(output(), output().contains("protocol version 2 requested, this agent speaks 1"));
        assertEquals(2, run(new PipedInputStream(new PipedOutputStream()), "socket"));
        assertFalse(output().contains("READY"));
        assertFalse(camera.closed);
    }

    @Test
    public void aCameraThatCannotOpenIsQuotedBeforeAnyReadyLine() throws Exception {
        platform.cameraFailure = new Exception("camera 0: ERROR_CAMERA_DISABLED");
        assertEquals(1, run(new PipedInputStream(new PipedOutputStream()), "socket=tbp-capture", "version=1"));
        assertTrue(output(), output().contains("cannot open the camera"));
        assertTrue(output(), output().contains("ERROR_CAMERA_DISABLED"));
        assertFalse(output().contains("READY"));
    }

    @Test
    public void anImageFolderThatCannotBeCreatedFailsTheStart() throws Exception {
        final File blocker = Fakes.folder();
        assertTrue(blocker.createNewFile());  // a file where the folder should be
        Platform blocked = new Fakes.FakePlatform(camera) {
            @Override
            public ImageStore imageStore() {
                return new ImageStore(blocker, new Fakes.Disk());
            }

            @Override
            public Closeable listen(String name, Agent agent) {
                throw new AssertionError("listened without an image folder");
            }
        };
        int status = Launcher.run(new String[] {"version=1"}, blocked, new PipedInputStream(new PipedOutputStream()),
                new PrintStream(printed, true));
        assertEquals(1, status);
        assertTrue(output(), output().contains("cannot create"));
        assertTrue(camera.closed);
    }
}
